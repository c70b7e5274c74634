"""Bag-of-words image index: TF-IDF vectors, an inverted file, L1 scores (as DBoW2 scores them).

The inverted file is held as numpy arrays so that a query is a handful of vectorised operations however many
words it has: the postings of all but the newest images sorted by word (CSR: `_start[w]` .. `_start[w + 1]`),
and the newest images (from `_sorted` on) as they came, merged into the sorted part every TAIL images."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

TAIL = 32  # images kept unsorted before a merge: a merge copies every posting, a query scans the tail


@dataclass(frozen=True)
class BowVector:
    """One image's L1-normalised TF-IDF vector: its words (sorted, unique) and their weights."""
    words: np.ndarray  # (K,) int64
    weights: np.ndarray  # (K,) float64, summing to 1

    def __len__(self) -> int:
        return len(self.words)


def l1_score(a: BowVector, b: BowVector) -> float:
    """1 - |a - b|_1 / 2 for L1-normalised vectors: 1 identical, 0 no word in common."""
    _, ia, ib = np.intersect1d(a.words, b.words, assume_unique=True, return_indices=True)
    return float(np.minimum(a.weights[ia], b.weights[ib]).sum())


class BowIndex:
    def __init__(self, n_words: int) -> None:
        self.n_words = n_words
        self.vectors: list[BowVector] = []
        self._start = np.zeros(n_words + 1, np.int64)  # CSR over images [0, _sorted)
        self._img = np.zeros(0, np.int64)
        self._w = np.zeros(0)
        self._sorted = 0
        # the tail's postings (word, image, weight) in image order, appended as images come: a query reads them
        # as they are instead of concatenating the tail's vectors again
        self._tail = (np.zeros(64, np.int64), np.zeros(64, np.int64), np.zeros(64))
        self._tail_n = 0

    def __len__(self) -> int:
        return len(self.vectors)

    def add(self, v: BowVector) -> int:
        self.vectors.append(v)
        n, k = self._tail_n, len(v)
        if n + k > len(self._tail[0]):
            self._tail = tuple(np.resize(a, max(2 * len(a), n + k)) for a in self._tail)
        words, img, w = self._tail
        words[n:n + k], img[n:n + k], w[n:n + k] = v.words, len(self.vectors) - 1, v.weights
        self._tail_n = n + k
        if len(self.vectors) - self._sorted >= TAIL:
            self._merge()
        return len(self.vectors) - 1

    def _tail_postings(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The unsorted images' postings as flat (word, image, weight) arrays, in image order."""
        n = self._tail_n
        return self._tail[0][:n], self._tail[1][:n], self._tail[2][:n]

    def _merge(self) -> None:
        """Move the tail into the sorted postings: each word's new images go after its old ones."""
        words, img, w = self._tail_postings()
        order = np.argsort(words, kind="stable")  # by word, then by image (the tail is in image order)
        words, img, w = words[order], img[order], w[order]
        old_count = np.diff(self._start)
        add_count = np.bincount(words, minlength=self.n_words)
        start = np.zeros_like(self._start)
        np.cumsum(old_count + add_count, out=start[1:])
        n = start[-1]
        new_img, new_w = np.empty(n, np.int64), np.empty(n)
        # an old posting of word x moves by the tail postings of the words before x
        shift = np.repeat(start[:-1] - self._start[:-1], old_count)
        pos_old = np.arange(len(self._img)) + shift
        new_img[pos_old], new_w[pos_old] = self._img, self._w
        # a tail posting goes after its word's old ones, in order
        first = np.searchsorted(words, words)  # index of the word's first tail posting
        pos_new = start[words] + old_count[words] + (np.arange(len(words)) - first)
        new_img[pos_new], new_w[pos_new] = img, w
        self._start, self._img, self._w, self._sorted = start, new_img, new_w, len(self.vectors)
        self._tail_n = 0

    def query(self, v: BowVector, allowed, top: int) -> list[tuple[int, float]]:
        """Best `top` entries (index, score) among those with allowed(index) true."""
        if not self.vectors or not len(v):
            return []
        n = len(self.vectors)
        # (gathers by `take`, the ranking on Python floats: the same scores, ~7 % less time)
        # sorted part: gather the postings of the query's words (ranges of the CSR arrays)
        lo = self._start.take(v.words)
        counts = self._start.take(v.words + 1) - lo
        total = int(counts.sum())
        if total:
            offs = (lo - counts.cumsum() + counts).repeat(counts) + np.arange(total)
            x = v.weights.repeat(counts)
            # |x - y| - x - y = -2 min(x, y): the L1 score over the words both hold
            acc = np.bincount(self._img.take(offs), np.minimum(x, self._w.take(offs)), minlength=n)
        else:
            acc = np.zeros(n)
        # tail: a dense lookup of the query's weights
        if self._sorted < n:
            dense = np.zeros(self.n_words)
            dense[v.words] = v.weights
            words, img, w = self._tail_postings()
            acc += np.bincount(img, np.minimum(dense.take(words), w), minlength=n)
        order = (-acc).argsort(kind="stable").tolist()  # best score first
        scores = acc.tolist()
        out = []
        for i in order:
            if scores[i] <= 0:
                break
            if allowed(i):
                out.append((i, scores[i]))
                if len(out) == top:
                    break
        return out
