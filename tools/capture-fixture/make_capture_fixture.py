#!/usr/bin/env python3
"""Writes the AIST++-style capture fixtures of lifegom_data::capture's tests.

AIST++ ships each dance as a pickle of a dict of numpy arrays: `smpl_poses` [frames, 72]
(SMPL axis-angle, radians), `smpl_trans` [frames, 3] and `smpl_scaling` [1] (the file's units
per metre), plus `smpl_loss`. This script writes the same structure with Python's own `pickle`
and numpy (a made-up motion: AIST++ data is not redistributed here), and the same arrays as an
`.npz` with `numpy.savez_compressed`:

- 30 frames at AIST++'s 60 fps; the left knee (SMPL joint 4) bends from 0 to 1 rad about x,
  both shoulders lower the arms, and the body walks 0.9 units a frame along +z, with
  `smpl_scaling` 90 (so 1 cm a frame).

    /usr/bin/python3 tools/capture-fixture/make_capture_fixture.py tests/fixtures/capture

Needs numpy.
"""

import os
import pickle
import sys

import numpy as np


def main():
    out = sys.argv[1]
    frames = 30
    poses = np.zeros((frames, 72), dtype=np.float64)
    t = np.arange(frames) / (frames - 1)
    poses[:, 4 * 3 + 0] = t  # left knee flexion, 0 -> 1 rad
    poses[:, 16 * 3 + 2] = -1.2 * t  # left shoulder: arm down
    poses[:, 17 * 3 + 2] = 1.2 * t  # right shoulder: arm down
    trans = np.zeros((frames, 3), dtype=np.float64)
    trans[:, 1] = 80.0  # pelvis height in the file's units
    trans[:, 2] = 0.9 * np.arange(frames)
    motion = {
        "smpl_loss": 1.5,
        "smpl_poses": poses,
        "smpl_scaling": np.array([90.0]),
        "smpl_trans": trans,
    }
    with open(os.path.join(out, "aist_like.pkl"), "wb") as f:
        pickle.dump(motion, f)
    np.savez_compressed(os.path.join(out, "aist_like.npz"), **motion)
    print(f"{out}: aist_like.pkl, aist_like.npz ({frames} frames), numpy {np.__version__}")


if __name__ == "__main__":
    main()
