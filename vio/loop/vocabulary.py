"""A vocabulary tree over 256-bit binary descriptors (ORB), built by k-majority clustering.

Nodes are stored in heap order: node i has children i*k+1 .. i*k+k; the leaves of the last level are the
words. A descriptor descends by Hamming distance to the children's centres. Word weights are inverse
document frequencies over the training images. The file is a plain npz (`save`/`load`), no pickle.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vio import VioError

FORMAT_VERSION = 1
DEFAULT_PATH = Path(__file__).with_name("data") / "vocabulary.npz"
_POPCOUNT = np.array([bin(i).count("1") for i in range(256)], np.uint8)


def hamming_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamming distances between 32-byte descriptors broadcast against each other (..., 32) -> (...): XOR and
    popcount on 64-bit words (numpy >= 2), 8x fewer operations than a byte lookup table."""
    if hasattr(np, "bitwise_count"):
        x = np.bitwise_xor(np.ascontiguousarray(a).view(np.uint64), np.ascontiguousarray(b).view(np.uint64))
        return np.bitwise_count(x).sum(-1, dtype=np.int32)
    return _POPCOUNT[np.bitwise_xor(a, b)].sum(-1, dtype=np.int32)


def unpack(desc: np.ndarray) -> np.ndarray:
    """(N, 32) uint8 descriptors -> (N, 256) float32 bits."""
    return np.unpackbits(np.asarray(desc, np.uint8), axis=1).astype(np.float32)


def hamming_bits(a_bits: np.ndarray, c_bits: np.ndarray) -> np.ndarray:
    """Hamming distances (N, M) between unpacked bit rows: |a| + |c| - 2 a.c."""
    return a_bits.sum(1)[:, None] + c_bits.sum(1)[None, :] - 2.0 * (a_bits @ c_bits.T)


def _k_majority(bits: np.ndarray, k: int, rng: np.random.Generator, iters: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """k-majority clustering (k-means with Hamming distance and bitwise-majority centres), k-means++ seeds."""
    n = len(bits)
    idx = [int(rng.integers(n))]
    d = hamming_bits(bits, bits[idx[-1]][None])[:, 0]
    for _ in range(1, k):
        p = d ** 2
        idx.append(int(rng.choice(n, p=p / p.sum())) if p.sum() > 0 else int(rng.integers(n)))
        d = np.minimum(d, hamming_bits(bits, bits[idx[-1]][None])[:, 0])
    centres = bits[idx].copy()
    assign = np.zeros(n, np.int64)
    for _ in range(iters):
        assign = np.argmin(hamming_bits(bits, centres), axis=1)
        for j in range(k):
            members = bits[assign == j]
            if len(members):
                centres[j] = (members.mean(0) >= 0.5).astype(np.float32)
    return centres, assign


@dataclass(frozen=True)
class Vocabulary:
    k: int  # branching factor
    depth: int  # levels below the root; k**depth words
    centres: np.ndarray  # (n_nodes, 32) uint8, heap order, root unused
    idf: np.ndarray  # (k**depth,) float32 word weights

    @property
    def n_words(self) -> int:
        return self.k ** self.depth

    @property
    def first_leaf(self) -> int:
        return (self.k ** self.depth - 1) // (self.k - 1)

    def words(self, desc: np.ndarray) -> np.ndarray:
        """Word id of each descriptor (N,)."""
        if len(desc) == 0:
            return np.zeros(0, np.int64)
        d = np.ascontiguousarray(desc, np.uint8)[:, None, :]
        node = np.zeros(len(d), np.int64)
        for _ in range(self.depth):
            children = node[:, None] * self.k + 1 + np.arange(self.k)[None, :]  # (N, k)
            dist = hamming_rows(d, self.centres[children])  # (N, k)
            node = children[np.arange(len(d)), np.argmin(dist, axis=1)]
        return node - self.first_leaf

    def bow(self, desc: np.ndarray) -> dict[int, float]:
        """L1-normalised TF-IDF vector of one image, as {word: weight}."""
        w = self.words(desc)
        if len(w) == 0:
            return {}
        ids, counts = np.unique(w, return_counts=True)
        v = counts / len(w) * self.idf[ids]
        s = v.sum()
        return {int(i): float(x / s) for i, x in zip(ids, v) if x > 0} if s > 0 else {}

    def save(self, path: str | Path) -> None:
        np.savez_compressed(path, format_version=np.int64(FORMAT_VERSION), k=np.int64(self.k),
                            depth=np.int64(self.depth), centres=self.centres, idf=self.idf)

    @staticmethod
    def load(path: str | Path | None = None) -> Vocabulary:
        path = Path(path) if path else DEFAULT_PATH
        try:
            with np.load(path, allow_pickle=False) as z:
                if int(z["format_version"]) != FORMAT_VERSION:
                    raise VioError(f"{path}: vocabulary format {int(z['format_version'])}, expected {FORMAT_VERSION}")
                return Vocabulary(int(z["k"]), int(z["depth"]), z["centres"].astype(np.uint8),
                                  z["idf"].astype(np.float32))
        except (OSError, KeyError, ValueError) as e:
            raise VioError(f"{path}: cannot read the vocabulary ({e})") from None


def train(images_desc: list[np.ndarray], k: int = 8, depth: int = 4, seed: int = 0,
          max_descriptors: int = 60000) -> Vocabulary:
    """Build a vocabulary from per-image descriptor arrays (the IDF is counted over these images)."""
    rng = np.random.default_rng(seed)
    all_desc = np.concatenate([d for d in images_desc if len(d)])
    if len(all_desc) > max_descriptors:
        all_desc = all_desc[rng.choice(len(all_desc), max_descriptors, replace=False)]
    n_nodes = (k ** (depth + 1) - 1) // (k - 1)
    cbits = np.zeros((n_nodes, 256), np.float32)
    bits = unpack(all_desc)
    todo = [(0, np.arange(len(bits)))]
    while todo:
        node, members = todo.pop()
        first_child = node * k + 1
        if first_child >= n_nodes:
            continue
        sub = bits[members]
        if len(sub) >= k:
            centres, assign = _k_majority(sub, k, rng)
        else:  # too few descriptors: children repeat the parent (they still descend consistently)
            centres = np.repeat(cbits[node][None] if len(sub) == 0 else sub[:1], k, axis=0)
            assign = np.zeros(len(sub), np.int64)
        for j in range(k):
            cbits[first_child + j] = centres[j]
            todo.append((first_child + j, members[assign == j]))
    centres = np.packbits(cbits.astype(np.uint8), axis=1)
    voc = Vocabulary(k, depth, centres, np.ones(k ** depth, np.float32))
    df = np.zeros(voc.n_words)
    for d in images_desc:
        if len(d):
            df[np.unique(voc.words(d))] += 1
    idf = np.log(len(images_desc) / np.maximum(df, 1.0)).astype(np.float32)
    idf[df == 0] = float(np.log(len(images_desc)))
    return Vocabulary(k, depth, centres, idf)
