"""Bag-of-words image index: TF-IDF vectors, an inverted file, L1 scores (as DBoW2 scores them)."""

from __future__ import annotations

from collections import defaultdict


def l1_score(a: dict[int, float], b: dict[int, float]) -> float:
    """1 - |a - b|_1 / 2 for L1-normalised vectors: 1 identical, 0 no word in common."""
    return -0.5 * sum(abs(a[w] - b[w]) - a[w] - b[w] for w in a.keys() & b.keys())


class BowIndex:
    def __init__(self) -> None:
        self.vectors: list[dict[int, float]] = []
        self.inverted: dict[int, list[int]] = defaultdict(list)

    def __len__(self) -> int:
        return len(self.vectors)

    def add(self, v: dict[int, float]) -> int:
        i = len(self.vectors)
        self.vectors.append(v)
        for w in v:
            self.inverted[w].append(i)
        return i

    def query(self, v: dict[int, float], allowed, top: int) -> list[tuple[int, float]]:
        """Best `top` entries (index, score) among those with allowed(index) true."""
        acc: dict[int, float] = defaultdict(float)
        for w, x in v.items():
            for i in self.inverted.get(w, ()):
                y = self.vectors[i][w]
                acc[i] += abs(x - y) - x - y
        scored = [(i, -0.5 * s) for i, s in acc.items() if allowed(i)]
        scored.sort(key=lambda t: -t[1])
        return scored[:top]
