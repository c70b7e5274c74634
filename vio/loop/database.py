"""Bag-of-words image index: TF-IDF vectors, an inverted file, L1 scores (as DBoW2 scores them)."""

from __future__ import annotations

import numpy as np


def l1_score(a: dict[int, float], b: dict[int, float]) -> float:
    """1 - |a - b|_1 / 2 for L1-normalised vectors: 1 identical, 0 no word in common."""
    return -0.5 * sum(abs(a[w] - b[w]) - a[w] - b[w] for w in a.keys() & b.keys())


class BowIndex:
    """Inverted file: per word, the images that hold it and their weights (numpy arrays grown by doubling,
    so that a query is a few array slices and one bincount, not a Python loop over postings)."""

    def __init__(self) -> None:
        self.vectors: list[dict[int, float]] = []
        self._post: dict[int, list] = {}  # word -> [ids array, weights array, used length]

    def __len__(self) -> int:
        return len(self.vectors)

    def add(self, v: dict[int, float]) -> int:
        i = len(self.vectors)
        self.vectors.append(v)
        post = self._post
        for w, x in v.items():
            p = post.get(w)
            if p is None:
                post[w] = p = [np.empty(8, np.int64), np.empty(8), 0]
            n = p[2]
            if n == len(p[0]):
                ids, ws = np.empty(2 * n, np.int64), np.empty(2 * n)
                ids[:n], ws[:n] = p[0], p[1]
                p[0], p[1] = ids, ws
            p[0][n] = i
            p[1][n] = x
            p[2] = n + 1
        return i

    def query(self, v: dict[int, float], allowed, top: int) -> list[tuple[int, float]]:
        """Best `top` entries (index, score) among those with allowed(index) true."""
        if not self.vectors or not v:
            return []
        ids, ys, xs, lens = [], [], [], []
        post = self._post
        for w, x in v.items():
            p = post.get(w)
            if p is not None:
                n = p[2]
                ids.append(p[0][:n])
                ys.append(p[1][:n])
                xs.append(x)
                lens.append(n)
        if not ids:
            return []
        # |x - y| - x - y = -2 min(x, y): the L1 score over the words both hold, one vectorised pass
        y = np.concatenate(ys)
        acc = np.bincount(np.concatenate(ids), -2.0 * np.minimum(np.repeat(xs, lens), y), minlength=len(self.vectors))
        order = np.argsort(acc)  # most negative sum = best score
        out = []
        for i in order:
            if acc[i] >= 0:
                break
            if allowed(int(i)):
                out.append((int(i), float(-0.5 * acc[i])))
                if len(out) == top:
                    break
        return out
