"""`vio loop train-vocab DATASET... -o FILE`: build the place-recognition vocabulary from recorded images;
`vio loop test-vocab DATASET`: retrieval on images the vocabulary was not trained on (docs/loop-closure.md)."""

from __future__ import annotations

import argparse

import numpy as np


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="loop_command", metavar="ACTION", required=True)
    t = sub.add_parser("train-vocab", help="train the vocabulary tree (k-majority) on EuRoC datasets' cam0 images")
    t.add_argument("datasets", nargs="+", metavar="DATASET")
    t.add_argument("-o", "--output", required=True, metavar="NPZ")
    t.add_argument("--every", type=int, default=10, help="use every Nth image (default: 10)")
    t.add_argument("--branching", type=int, default=8)
    t.add_argument("--depth", type=int, default=4)
    t.add_argument("--features", type=int, default=300, help="ORB corners per image")


def _descriptors(dataset: str, every: int, n_features: int) -> list[np.ndarray]:
    import cv2

    from vio.io.euroc import EurocDataset
    from vio.loop.features import FeatureExtractor

    ds = EurocDataset(dataset)
    ex = FeatureExtractor(ds.calibration.cam0, n_features)
    out = []
    for f in ds.cam0_files[::every]:
        if f is None:
            continue
        img = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        if img is not None:
            out.append(ex.extract(img, None).desc)
    return out


def run(args: argparse.Namespace) -> int:
    from vio import VioError
    from vio.loop.vocabulary import train

    if args.loop_command == "train-vocab":
        desc = [d for ds in args.datasets for d in _descriptors(ds, args.every, args.features)]
        if len(desc) < 2:
            raise VioError("too few images to train a vocabulary")
        voc = train(desc, args.branching, args.depth)
        voc.save(args.output)
        print(f"vocabulary: {voc.n_words} words (k={voc.k}, depth {voc.depth}) from {len(desc)} images, "
              f"{sum(len(d) for d in desc)} descriptors -> {args.output}")
    return 0
