"""Writes the pickle fixtures of the `lifegom-data` pickle reader tests.

Run once per numpy major version (each in its own venv), e.g.

    python -m venv /tmp/np1 && /tmp/np1/bin/pip install "numpy<2"
    python -m venv /tmp/np2 && /tmp/np2/bin/pip install "numpy>=2"
    /tmp/np1/bin/python tools/make_pickle_fixtures.py tests/fixtures/pickle
    /tmp/np2/bin/python tools/make_pickle_fixtures.py tests/fixtures/pickle

It writes `np{1,2}_p{2,4,5}.pkl`: the same object at pickle protocols 2, 4 and 5. numpy 1.x
pickles name `numpy.core.multiarray`, numpy 2.x `numpy._core.multiarray`; protocol 5 makes numpy
use `_frombuffer` with an in-band PickleBuffer. Every value is a simple formula of its index so
the Rust test can recompute it without storing expected data (see data/tests/pickle_fixtures.rs).
"""
import pickle
import sys
from pathlib import Path

import numpy as np


def payload():
    k = np.array([[819.2, 0.0, 512.0], [0.0, 819.2, 537.0], [0.0, 0.0, 1.0]], dtype=np.float32)
    e = np.eye(4, dtype=np.float64)
    e[:3, 3] = [0.1, -0.2, 2.0]
    return {
        # dtypes, C order
        "f32": (np.arange(12, dtype=np.float32).reshape(3, 4) * 0.5 - 1.0),
        "f64": np.arange(6, dtype=np.float64).reshape(2, 3) / 3.0,
        "i32": np.arange(-3, 3, dtype=np.int32),
        "i64": np.arange(4, dtype=np.int64).reshape(2, 2) * (1 << 40),
        "u8": np.arange(250, 256, dtype=np.uint8),
        "bool": np.array([True, False, True]),
        # memory layouts and byte orders
        "f64_fortran": np.asfortranarray(np.arange(12, dtype=np.float64).reshape(3, 4)),
        "f32_big": np.arange(5, dtype=">f4") * 0.25,
        "i64_big": np.arange(-2, 2, dtype=">i8"),
        "i32_fortran_3d": np.asfortranarray(np.arange(24, dtype=np.int32).reshape(2, 3, 4)),
        # corner cases
        "empty": np.zeros((0, 3), dtype=np.float32),
        "zero_d": np.array(3.5, dtype=np.float64),
        "scalar_f32": np.float32(1.5),
        "scalar_i64": np.int64(-7),
        "py": [1, -2, 2**40, 2.5, "text", None, True, (1, 2)],
        # the official file shapes, in miniature
        "cameras": {"frame_000000": {"intrinsics": k, "extrinsics": e}},
        "mesh_infos": {
            "frame_000000": {
                "poses": np.zeros(72, dtype=np.float32),
                "tpose_joints": np.arange(72, dtype=np.float32).reshape(24, 3) * 0.01,
                "Rh": np.array([[0.0, 0.5, 0.0]], dtype=np.float32),
                "Th": np.array([0.0, 0.9, 0.0], dtype=np.float32),
            }
        },
        "canonical_joints": {
            "joints": np.arange(72, dtype=np.float32).reshape(24, 3) * 0.01,
            "faces": np.array([[0, 1, 2], [2, 1, 3]], dtype=np.int64),
            "weights": np.full((4, 24), 1.0 / 24.0, dtype=np.float32),
        },
    }


def main():
    out = Path(sys.argv[1])
    out.mkdir(parents=True, exist_ok=True)
    major = np.__version__.split(".")[0]
    for protocol in (2, 4, 5):
        path = out / f"np{major}_p{protocol}.pkl"
        with open(path, "wb") as f:
            pickle.dump(payload(), f, protocol=protocol)
        with open(path, "rb") as f:
            back = pickle.load(f)
        assert np.array_equal(back["f64_fortran"], payload()["f64_fortran"])
        print(path, path.stat().st_size, "bytes, numpy", np.__version__)


if __name__ == "__main__":
    main()
