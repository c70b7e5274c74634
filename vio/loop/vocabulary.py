"""A vocabulary tree over 256-bit binary descriptors (ORB), built by k-majority clustering.

Nodes are stored in heap order: node i has children i*k+1 .. i*k+k; the leaves of the last level are the
words. A descriptor descends by Hamming distance to the children's centres. Word weights are inverse
document frequencies over the training images. The file is a plain npz (`save`/`load`), no pickle.
"""

from __future__ import annotations

import os
import stat
import tokenize
import zipfile
import zlib
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from vio import VioError
from vio.loop.database import BowVector

# what numpy and zipfile raise for an .npz archive cut short or damaged on disk: a byte flipped inside a compressed
# array (zlib), in an array's header (numpy's header parser: TokenError) or in the archive's directory (zipfile:
# "zip file version 21.0"); maps (vio.loop.mapfile) are .npz archives too
NPZ_DAMAGED = (zipfile.BadZipFile, EOFError, zlib.error, tokenize.TokenError, NotImplementedError)


def load_npz(path: str | Path, what: str):
    """np.load of a vocabulary's or a map's file, refusing anything but a regular file first: on a pipe np.load
    waited for ever for a writer (`vio map info`, `vio run`'s start check, and `vio replay` / `vio run` with [loop]
    vocabulary naming one, hung). A folder is left to np.load, which says so. OSError (no such file) as np.load's."""
    mode = os.stat(path).st_mode
    if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
        raise VioError(f"{path}: is not a regular file (a device, pipe or socket), not {what}")
    return np.load(path, allow_pickle=False)

FORMAT_VERSION = 1
DEFAULT_PATH = Path(__file__).with_name("data") / "vocabulary.npz"
_POPCOUNT = np.array([bin(i).count("1") for i in range(256)], np.uint8)


def popcount_u64(x: np.ndarray) -> np.ndarray:
    """Set bits of each uint64 (numpy >= 2 counts them natively; older numpy through a byte table)."""
    if hasattr(np, "bitwise_count"):
        return np.bitwise_count(x)
    return _POPCOUNT[np.ascontiguousarray(x).view(np.uint8)].reshape(*x.shape, 8).sum(-1, dtype=np.uint8)


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

    @cached_property
    def _blocks(self) -> np.ndarray:
        """(n_nodes // k, 4k) uint64: row n holds node n's k children, each descriptor as four 64-bit words."""
        return np.ascontiguousarray(self.centres[1:]).view(np.uint64).reshape(-1, self.k * 4)

    @cached_property
    def _sum4(self) -> np.ndarray:
        """(4k, k) 0/1: sums each child's four per-word bit counts (one matrix product for all descriptors)."""
        return np.kron(np.eye(self.k, dtype=np.float32), np.ones((4, 1), np.float32))

    def words(self, desc: np.ndarray) -> np.ndarray:
        """Word id of each descriptor (N,): descend by the Hamming distance to the children's centres, all
        descriptors at once (XOR and popcount on 64-bit words)."""
        if len(desc) == 0:
            return np.zeros(0, np.int64)
        d = np.tile(np.ascontiguousarray(desc, np.uint8).view(np.uint64), (1, self.k))  # (N, 4k)
        blocks = self._blocks
        node = np.zeros(len(d), np.int64)
        for level in range(self.depth):
            # the root's children for every descriptor by broadcasting, then each one's node gathered by `take`
            # (fancy indexing and a gather of the same row N times cost 17 % more of this function on the shelves
            # flight's keyframes; the same distances)
            children = blocks[:1] if level == 0 else blocks.take(node, axis=0)
            dist = popcount_u64(np.bitwise_xor(children, d)).astype(np.float32) @ self._sum4  # (N, k)
            node = node * self.k + 1 + dist.argmin(axis=1)
        return node - self.first_leaf

    def bow(self, desc: np.ndarray) -> BowVector:
        """L1-normalised TF-IDF vector of one image (words of weight 0 left out)."""
        w = self.words(desc)
        ids, counts = np.unique(w, return_counts=True)
        v = counts / max(len(w), 1) * self.idf[ids]
        keep = v > 0
        s = v[keep].sum()
        if s <= 0:
            return BowVector(np.zeros(0, np.int64), np.zeros(0))
        return BowVector(ids[keep].astype(np.int64), v[keep] / s)

    def save(self, path: str | Path) -> None:
        """Written under exactly `path` (numpy's savez given a name adds .npz to one without: the file written
        was not the one the command named)."""
        with open(path, "wb") as f:
            np.savez_compressed(f, format_version=np.int64(FORMAT_VERSION), k=np.int64(self.k),
                                depth=np.int64(self.depth), centres=self.centres, idf=self.idf)

    @staticmethod
    def load(path: str | Path | None = None) -> Vocabulary:
        path = Path(path) if path else DEFAULT_PATH
        try:
            with load_npz(path, "a vocabulary file") as z:
                if int(z["format_version"]) != FORMAT_VERSION:
                    raise VioError(f"{path}: vocabulary format {int(z['format_version'])}, expected {FORMAT_VERSION}")
                k, depth, centres, idf = int(z["k"]), int(z["depth"]), z["centres"], z["idf"]
                problem = _arrays_problem(k, depth, centres, idf)
                if problem:
                    raise VioError(f"{path}: not a vocabulary of ORB descriptors this program can use ({problem}); "
                                   "train one with `vio loop train-vocab`, or leave [loop] vocabulary empty for the "
                                   "packaged one")
                return Vocabulary(k, depth, centres.astype(np.uint8), idf.astype(np.float32))
        except (OSError, KeyError, ValueError) as e:
            raise VioError(f"{path}: cannot read the vocabulary ({e})") from None
        except NPZ_DAMAGED:  # one line (it ended in "internal error" from vio replay/run)
            raise VioError(f"{path}: cannot read the vocabulary (not a complete .npz archive: a truncated or "
                           "damaged file; train it again with `vio loop train-vocab`, or leave [loop] vocabulary "
                           "empty for the packaged one)") from None


def _arrays_problem(k: int, depth: int, centres: np.ndarray, idf: np.ndarray) -> str | None:
    """What in a vocabulary file's arrays does not fit a k-branch, depth-level tree over 256-bit ORB descriptors, or
    None. Unchecked, a tree of 512-bit or float descriptors (another feature's vocabulary) loaded and retrieved
    nothing, silently, and a k or idf that did not fit the centres stopped the loop stage mid-flight on an
    IndexError or ZeroDivisionError, leaving the flight without loop closure."""
    if k < 2 or depth < 1 or k ** depth > 1 << 24:
        return f"branching {k}, depth {depth}: a tree needs branching >= 2 and depth >= 1"
    n_nodes = (k ** (depth + 1) - 1) // (k - 1)
    if centres.dtype != np.uint8 or centres.shape != (n_nodes, 32):
        return (f"node centres {centres.shape} {centres.dtype}, a tree of branching {k} and depth {depth} over "
                f"ORB descriptors needs ({n_nodes}, 32) uint8")
    if idf.shape != (k ** depth,) or not np.issubdtype(idf.dtype, np.floating) or not np.isfinite(idf).all() \
            or (idf < 0).any():
        return f"word weights {idf.shape} {idf.dtype}: {k ** depth} finite weights >= 0 needed"
    return None


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
