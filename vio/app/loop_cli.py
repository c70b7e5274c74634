"""`vio loop train-vocab DATASET... -o FILE`: build the place-recognition vocabulary from recorded images (how it
retrieves on images it was not trained on: `tests/test_loop.py::test_vocabulary_retrieves_the_same_place_in_unseen_
images`, docs/loop-closure.md)."""

from __future__ import annotations

import argparse
import logging
import math

import numpy as np

from vio.argtypes import int_at_least, positive_int

log = logging.getLogger(__name__)

# A tree of more words is no vocabulary: training samples at most 60000 descriptors, so most words stay empty, and
# its nodes (1 KB each while trained) outgrow a companion computer's memory (64^8 asked for 260 PiB: a MemoryError)
MAX_WORDS = 2**20
MAX_FEATURES = 100_000  # ORB corners per image (beyond a C int: an internal error in OpenCV)


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="loop_command", metavar="ACTION", required=True)
    t = sub.add_parser("train-vocab", help="train the vocabulary tree (k-majority) on EuRoC datasets' cam0 images")
    t.add_argument("datasets", nargs="+", metavar="DATASET")
    t.add_argument("-o", "--output", required=True, metavar="NPZ",
                   help="vocabulary file to write ([loop] vocabulary); written under exactly this name")
    t.add_argument("--overwrite", action="store_true", help="replace --output if it exists")
    t.add_argument("--every", type=positive_int, default=10, help="use every Nth image (default: 10)")
    t.add_argument("--branching", type=int_at_least(2), default=8, help="children per node (default: 8)")
    t.add_argument("--depth", type=positive_int, default=4,
                   help="levels below the root: branching^depth words (default: 4)")
    t.add_argument("--features", type=int_at_least(1, MAX_FEATURES), default=300, help="ORB corners per image")


def _descriptors(dataset: str, every: int, n_features: int) -> tuple[list[np.ndarray], int]:
    """ORB descriptors of every Nth left image, read as the replay reads them: a 16-bit recording scaled to 8 bits
    by the shift decided on its first image. cv2.imread's own 16 -> 8 bit conversion (>> 8) made 12-bit images
    near-black, and a vocabulary trained on them held 1 descriptor from 21 images. Also returns how many images
    were tried (the ones missing or unreadable are not in the list)."""
    from vio.io.euroc import EurocDataset
    from vio.loop.features import FeatureExtractor

    ds = EurocDataset(dataset)
    ex = FeatureExtractor(ds.calibration.cam0, n_features)
    out = []
    tried = range(0, len(ds), every)
    for i in tried:
        frame = ds.frame(i, lazy_right=True)  # None: the left image missing or unreadable (warned)
        if frame is not None:
            out.append(ex.extract(frame.left, None).desc)
    return out, len(tried)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from vio import UsageError, VioError
    from vio.io.outputs import check_new_file
    from vio.loop.vocabulary import train

    if args.loop_command == "train-vocab":
        if args.depth * math.log(args.branching) > math.log(MAX_WORDS):  # before any work; no k^d for a huge d
            raise UsageError(f"--branching {args.branching} --depth {args.depth}: {args.branching}^{args.depth} words, "
                             f"more than the {MAX_WORDS} a vocabulary can have (8^4 = 4096 by default)")
        out = Path(args.output)
        check_new_file(out, args.overwrite, *args.datasets)
        desc, tried = [], 0
        for ds in args.datasets:
            d, n = _descriptors(ds, args.every, args.features)
            desc, tried = desc + d, tried + n
        if len(desc) < 2:  # said with the counts: "too few images" over a folder of unreadable ones told nothing
            raise VioError(f"too few images to train a vocabulary: {len(desc)} of the {tried} left images taken "
                           f"(--every {args.every}) could be read, 2 or more needed"
                           + ("; the others are missing or unreadable (warned above)" if tried > len(desc) else
                              "; give more images or a smaller --every"))
        n_desc = sum(len(d) for d in desc)
        if n_desc < 2 * args.branching:
            # 2700 descriptors and --branching 10^11 were said as "no ORB corners to speak of"
            raise VioError(f"no ORB corners to speak of in the {len(desc)} images read ({n_desc} descriptors): "
                           "are they dark, blank or out of focus?" if n_desc < 16 else
                           f"--branching {args.branching} needs {2 * args.branching} descriptors or more, the "
                           f"{len(desc)} images read gave {n_desc}: use a smaller --branching or more images")
        voc = train(desc, args.branching, args.depth)
        if voc.n_words > n_desc:  # most words never hold a descriptor: retrieval by a handful of sparse words
            log.warning("%d words from %d descriptors: most words are empty and retrieval poor; use fewer levels "
                        "(--depth) or more images", voc.n_words, n_desc)
        voc.save(out)
        print(f"vocabulary: {voc.n_words} words (k={voc.k}, depth {voc.depth}) from {len(desc)} images, "
              f"{n_desc} descriptors -> {out}")
    return 0
