"""Loop closure: keyframe database, place recognition, geometric verification and a robust pose graph.

A stage beside the odometry (docs/loop-closure.md). It takes keyframes (left image, front-end features with
stereo depth, the odometry pose) and returns loop-corrected poses; it never changes the odometry. No threads
here: the application layer runs `LoopCloser` in its own thread (vio/app/loop_worker.py).

- features.py: keyframe image -> upright ORB descriptors, undistorted pixels, stereo 3D points;
- vocabulary.py: k-majority vocabulary tree on binary descriptors (trained by `vio loop train-vocab`);
- database.py: TF-IDF bag-of-words index with an inverted file;
- verify.py: 3D-2D PnP RANSAC, gravity (roll/pitch) check;
- posegraph.py: GTSAM pose graph in iSAM2 (odometry edges, attitude factors, inlier loop edges), loop edges
  decided by GNC (TLS) on a condensed graph of the loop-touched keyframes;
- closer.py: the stage (retrieval -> verification -> temporal consistency -> graph) and its correction;
- mapfile.py: versioned map file (npz arrays + JSON header) for save/load/relocalisation.
"""
