"""Bag-of-words image index: TF-IDF vectors, an inverted file, L1 scores (as DBoW2 scores them)."""

from __future__ import annotations

import numpy as np


def l1_score(a: dict[int, float], b: dict[int, float]) -> float:
    """1 - |a - b|_1 / 2 for L1-normalised vectors: 1 identical, 0 no word in common."""
    return -0.5 * sum(abs(a[w] - b[w]) - a[w] - b[w] for w in a.keys() & b.keys())


class BowIndex:
    """Inverted file: per word, the images that hold it and their weights (growing numpy arrays)."""

    def __init__(self) -> None:
        self.vectors: list[dict[int, float]] = []
        self._ids: dict[int, list[int]] = {}
        self._w: dict[int, list[float]] = {}

    def __len__(self) -> int:
        return len(self.vectors)

    def add(self, v: dict[int, float]) -> int:
        i = len(self.vectors)
        self.vectors.append(v)
        for w, x in v.items():
            self._ids.setdefault(w, []).append(i)
            self._w.setdefault(w, []).append(x)
        return i

    def query(self, v: dict[int, float], allowed, top: int) -> list[tuple[int, float]]:
        """Best `top` entries (index, score) among those with allowed(index) true."""
        if not self.vectors or not v:
            return []
        acc = np.zeros(len(self.vectors))
        for w, x in v.items():
            ids = self._ids.get(w)
            if ids:
                y = np.asarray(self._w[w])
                np.add.at(acc, np.asarray(ids), np.abs(x - y) - x - y)
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
