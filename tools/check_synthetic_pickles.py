"""Loads a generated synthetic split with plain Python + numpy, as the official LIFe-GoM loader
does (`pickle.load` of cameras.pkl, mesh_infos.pkl, canonical_joints.pkl), and checks types,
shapes and the camera/pose conventions. Not run by CI (no Python there); run it by hand:

    cargo run --release -p lifegom-data --bin lifegom-synth -- --config configs/synthetic-tiny.toml --out /tmp/synth-tiny
    python tools/check_synthetic_pickles.py /tmp/synth-tiny
"""
import json
import pickle
import sys
from pathlib import Path

import numpy as np


def rodrigues(v):
    theta = np.linalg.norm(v)
    r = v / (theta + 1e-5)
    k = np.array([[0, -r[2], r[1]], [r[2], 0, -r[0]], [-r[1], r[0], 0]])
    return np.eye(3) + np.sin(theta) * k + (1 - np.cos(theta)) * k @ k


def check_subject(d: Path):
    frames = sorted(p.stem for p in (d / "images").glob("*.png"))
    with open(d / "cameras.pkl", "rb") as f:
        cams = pickle.load(f)
    with open(d / "mesh_infos.pkl", "rb") as f:
        infos = pickle.load(f)
    with open(d / "canonical_joints.pkl", "rb") as f:
        cnl = pickle.load(f)
    j = cnl["joints"].shape[0]
    v = cnl["vertex"].shape[0]
    assert isinstance(cnl["vertex"], np.ndarray) and cnl["vertex"].dtype == np.float32
    assert cnl["weights"].shape == (v, j) and np.allclose(cnl["weights"].sum(1), 1, atol=1e-4)
    assert cnl["faces"].dtype == np.int64 and cnl["faces"].max() < v
    assert cnl["parents"].shape == (j,) and cnl["parents"][0] == -1
    assert len(cnl["joint_names"]) == j
    for name in frames:
        k = cams[name]["intrinsics"]
        e = cams[name]["extrinsics"]
        assert k.shape == (3, 3) and e.shape == (4, 4) and k.dtype == np.float32
        assert np.allclose(e[:3, :3] @ e[:3, :3].T, np.eye(3), atol=1e-5)
        mi = infos[name]
        assert mi["poses"].shape == (3 * j,) and mi["tpose_joints"].shape == (j, 3)
        # The pelvis, moved by Rh/Th and seen by E (the official folding), is ~2 m ahead.
        pelvis = rodrigues(mi["Rh"]) @ cnl["joints"][0] + mi["Th"]
        cam = e[:3, :3] @ pelvis + e[:3, 3]
        assert 1.5 < cam[2] < 2.5, cam
        u, vv = (k @ (cam / cam[2]))[:2]
        assert 0 <= u < 1e4 and 0 <= vv < 1e4
    return len(frames), j, v


def main():
    root = Path(sys.argv[1])
    total = 0
    for split, names in (("train", "view3_train"), ("val", "view3_val")):
        subjects = json.loads((root / f"{split}.json").read_text())
        for s in subjects:
            n, j, v = check_subject(root / names / s)
            total += n
            print(f"{names}/{s}: {n} frames, {j} joints, {v} vertices: ok")
    print(f"numpy {np.__version__}: {total} frames checked")


if __name__ == "__main__":
    main()
