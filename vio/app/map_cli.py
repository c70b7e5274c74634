"""`vio map info FILE`: what a saved loop-closure map holds (format: docs/loop-closure.md#map-files)."""

from __future__ import annotations

import argparse
import json
import math


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="map_command", metavar="ACTION", required=True)
    i = sub.add_parser("info", help="print a map file's header and extent")
    i.add_argument("file", metavar="FILE")
    i.add_argument("--json", action="store_true", help="the header and figures as JSON")


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from vio.loop.closer import WEAK_JOIN_EDGES
    from vio.loop.mapfile import load_map, part_ranges

    m = load_map(args.file)
    p = m.T_world_body[:, :3, 3] if len(m.T_world_body) else np.zeros((0, 3))
    n3 = sum(f.n_3d for f in m.features)
    # a grown map's parts are flights on clocks of their own (the host's monotonic clock since each boot): the
    # time flown is summed part by part, never taken from the first stamp to the last
    spans = [float((m.t_ns[b - 1] - m.t_ns[a]) * 1e-9) if b - a > 1 else 0.0
             for a, b in part_ranges(m.header, len(m.t_ns))]
    # a map without parts may hold several flights on clocks of their own: stamps that run back say so
    mixed = not (m.header.get("parts") or []) and bool(np.any(np.diff(m.t_ns) <= 0))
    # the counts from the keyframes themselves (the header's are what the saver wrote; a hand-edited or foreign
    # header may lack them, as it may lack the informative created_utc and vocabulary: said, not a traceback)
    info = {**m.header, "keyframes": len(m.t_ns), "descriptors": int(sum(len(f.desc) for f in m.features)),
            "landmarks_3d": int(n3),
            "extent_m": {"min": p.min(0).round(3).tolist(), "max": p.max(0).round(3).tolist()} if len(p) else None,
            "span_s": None if mixed else round(sum(spans), 3),
            "part_spans_s": None if mixed else [round(x, 3) for x in spans]}
    if args.json:
        # a header's NaN or Infinity (json reads them; a hand-edited or foreign header) printed as such is not JSON: a
        # reader (jq, Python's json with strict parsing) failed on the whole output. Null, as JSON has no such number
        print(json.dumps(_finite(info), indent=1, allow_nan=False))
        return 0
    print(f"{args.file}: {info['format']} version {info.get('version', 0)}, created "
          f"{info.get('created_utc') or 'at an unknown time'}")
    if mixed:
        flown = "an unknown time (stamps of several flights, and no parts in the header to split them)"
    else:
        flown = f"{info['span_s']:.1f} s" + (f" of flight in {len(spans)} parts" if len(spans) > 1 else "")
    print(f"  {info['keyframes']} keyframes over {flown}, {info['descriptors']} descriptors, {n3} with stereo 3D "
          "points")
    if info["extent_m"]:
        print(f"  extent [m]: {info['extent_m']['min']} .. {info['extent_m']['max']}")
    v = info.get("vocabulary")
    if isinstance(v, dict) and all(isinstance(v.get(k), t) for k, t in (("k", int), ("depth", int), ("sha256", str))):
        print(f"  vocabulary k={v['k']} depth {v['depth']} sha256 {v['sha256'][:16]}...")
    else:
        print("  vocabulary: not stated in the header")
    c = info["camera"]
    print(f"  camera {c['width']}x{c['height']} fx {c['fx']:.1f} fy {c['fy']:.1f}")
    for k, part in enumerate(info.get("parts") or []):
        j = part.get("join_edges")  # optional: the loader takes a part without it as the origin
        how = "the frame's origin" if j is None else f"joined by {j} loop edges" + (
            " (weak: its place rests on them)" if j < WEAK_JOIN_EDGES else "")
        print(f"  part {k + 1}: {part['keyframes']} keyframes over {spans[k]:.1f} s, {how}")
    cp = info.get("checkpoint")
    if cp:
        print(f"  checkpoint of a run that did not stop cleanly (pid {cp.get('pid')}, started {cp.get('started_utc')}, "
              f"boot {str(cp.get('boot_id'))[:8]}...): not a finished map; `vio run` restarted on that boot with "
              "this [map] save grows it")
    if info.get("note"):
        print(f"  note: {info['note']}")
    return 0


def _finite(x: object) -> object:
    """`x` with every NaN or infinite number (any depth of dicts and lists) as None."""
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_finite(v) for v in x]
    return x
