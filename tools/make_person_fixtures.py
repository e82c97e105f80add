#!/usr/bin/env python3
"""Reference results of MediaPipe's own BlazePose pipeline (the `mediapipe` 0.10.14 Python
package, `pose_landmark_cpu` graph, model complexity 1 = `pose_landmark_full.tflite`), for the
parity tests of `lifegom-estimate`'s person pipeline (estimate/tests/person_parity.rs).

What it makes (under --out, default estimate/tests/fixtures/person/):

- `NAME.png`: each photo as given (8-bit RGB), which the Rust tests read.
- `NAME.json`: the pipeline's stages on it, as mediapipe reports them (image coordinates
  normalised to [0, 1] by the image's width and height):
  - `detection`: the first detection after weighted non-maximum suppression and letterbox
    removal: `score`, `box` (xmin, ymin, width, height) and its 4 `keypoints` (x, y);
  - `roi`: the landmark model's rotated crop from that detection (`x_center`, `y_center`,
    `width`, `height`, `rotation` in radians);
  - `landmarks`: the 33 body landmarks (x, y, z, visibility, presence);
  - `image_size`: [width, height].
- `NAME_mask.png`: the person segmentation, 16-bit grey, round(p · 65535) of the probability.
- `NAME_selfie.png`: the selfie model's segmentation through MediaPipe's own
  `solutions.selfie_segmentation.SelfieSegmentation(model_selection=0)` (the general 256 × 256
  model), the same encoding.
- `reference.json`: versions, the SHA-256 of the wheel and of every photo.

Photos: `astronaut` is scikit-image's `data/astronaut.png` (a NASA portrait, public domain),
read out of the scikit-image 0.25.2 wheel; `--image NAME=PATH` adds more (our renders).

Environment (CPU; Python 3.11; what the fixtures were made with):

    python3 -m venv /tmp/mpenv
    /tmp/mpenv/bin/pip install "numpy<2" pillow mediapipe==0.10.14

Run (seconds; downloads the scikit-image wheel with pip unless given):

    /tmp/mpenv/bin/python tools/make_person_fixtures.py \\
        [--skimage-wheel scikit_image-0.25.2-cp312-cp312-manylinux_2_17_x86_64.manylinux2014_x86_64.whl] \\
        [--image synth_front=front.png ...] [--out estimate/tests/fixtures/person]

Static-image mode: no tracking between photos, no smoothing (`use_prev_landmarks`,
`smooth_landmarks` and `smooth_segmentation` off), as `mediapipe.solutions.pose.Pose(
static_image_mode=True, enable_segmentation=True)` runs it.
"""

import argparse
import hashlib
import io
import json
import os
import subprocess
import sys
import tempfile
import zipfile

import numpy as np
from PIL import Image

SKIMAGE_SPEC = "scikit-image==0.25.2"
SKIMAGE_WHEEL = "scikit_image-0.25.2-cp312-cp312-manylinux_2_17_x86_64.manylinux2014_x86_64.whl"
SKIMAGE_SHA256 = "a17e17eb8562660cc0d31bb55643a4da996a81944b82c54805c91b3fe66f4824"
ASTRONAUT = "skimage/data/astronaut.png"
ASTRONAUT_SHA256 = "88431cd9653ccd539741b555fb0a46b61558b301d4110412b5bc28b5e3ea6cb5"


def sha256(data):
    return hashlib.sha256(data).hexdigest()


def astronaut(wheel):
    with tempfile.TemporaryDirectory() as tmp:
        if wheel is None:
            subprocess.run(
                [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary", ":all:",
                 "--platform", "manylinux2014_x86_64", "--python-version", "312",
                 "--dest", tmp, SKIMAGE_SPEC],
                check=True,
            )
            wheel = os.path.join(tmp, SKIMAGE_WHEEL)
        with open(wheel, "rb") as f:
            if sha256(f.read()) != SKIMAGE_SHA256:
                sys.exit(f"{wheel}: not the pinned {SKIMAGE_SPEC} wheel")
        with zipfile.ZipFile(wheel) as z:
            data = z.read(ASTRONAUT)
    if sha256(data) != ASTRONAUT_SHA256:
        sys.exit(f"{ASTRONAUT}: unexpected SHA-256")
    return data


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--skimage-wheel")
    ap.add_argument("--image", action="append", default=[], metavar="NAME=PATH")
    ap.add_argument("--out", default="estimate/tests/fixtures/person")
    args = ap.parse_args()

    import mediapipe
    from mediapipe.python.solution_base import SolutionBase
    from mediapipe.python.solutions import pose as mp_pose

    os.makedirs(args.out, exist_ok=True)
    photos = {"astronaut": astronaut(args.skimage_wheel)}
    for spec in args.image:
        name, path = spec.split("=", 1)
        with open(path, "rb") as f:
            photos[name] = f.read()

    solution = SolutionBase(
        binary_graph_path=mp_pose._BINARYPB_FILE_PATH,
        side_inputs={
            "model_complexity": 1,
            "smooth_landmarks": False,
            "enable_segmentation": True,
            "smooth_segmentation": False,
            "use_prev_landmarks": False,
        },
        outputs=["pose_landmarks", "segmentation_mask", "pose_detection", "pose_rect_from_detection"],
    )
    reference = {
        "versions": {"mediapipe": mediapipe.__version__, "numpy": np.__version__,
                     "python": sys.version.split()[0]},
        "photos": {},
    }
    for name, data in photos.items():
        image = Image.open(io.BytesIO(data)).convert("RGB")
        image.save(os.path.join(args.out, f"{name}.png"))
        with open(os.path.join(args.out, f"{name}.png"), "rb") as f:
            reference["photos"][name] = sha256(f.read())
        pixels = np.asarray(image)
        result = solution.process({"image": pixels})
        out = {"image_size": [image.width, image.height]}
        if result.pose_detection is not None:
            d = result.pose_detection
            box = d.location_data.relative_bounding_box
            out["detection"] = {
                "score": d.score[0],
                "box": [box.xmin, box.ymin, box.width, box.height],
                "keypoints": [[k.x, k.y] for k in d.location_data.relative_keypoints],
            }
        if result.pose_rect_from_detection is not None:
            r = result.pose_rect_from_detection
            out["roi"] = {"x_center": r.x_center, "y_center": r.y_center, "width": r.width,
                          "height": r.height, "rotation": r.rotation}
        if result.pose_landmarks is not None:
            out["landmarks"] = [[l.x, l.y, l.z, l.visibility, l.presence]
                                for l in result.pose_landmarks.landmark]
        if result.segmentation_mask is not None:
            mask = np.clip(np.round(result.segmentation_mask * 65535.0), 0, 65535).astype(np.uint16)
            Image.fromarray(mask).save(os.path.join(args.out, f"{name}_mask.png"))
        with open(os.path.join(args.out, f"{name}.json"), "w") as f:
            json.dump(out, f, indent=1)
            f.write("\n")
    solution.close()
    from mediapipe.python.solutions import selfie_segmentation
    with selfie_segmentation.SelfieSegmentation(model_selection=0) as selfie:
        for name in photos:
            pixels = np.asarray(Image.open(os.path.join(args.out, f"{name}.png")).convert("RGB"))
            mask = selfie.process(pixels).segmentation_mask
            mask = np.clip(np.round(mask * 65535.0), 0, 65535).astype(np.uint16)
            Image.fromarray(mask).save(os.path.join(args.out, f"{name}_selfie.png"))
    with open(os.path.join(args.out, "reference.json"), "w") as f:
        json.dump(reference, f, indent=1, sort_keys=True)
        f.write("\n")


if __name__ == "__main__":
    main()
