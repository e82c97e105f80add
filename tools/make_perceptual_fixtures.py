#!/usr/bin/env python3
"""Reference outputs of the pip `lpips` (v0.1, alex and vgg) and `pytorch-fid` packages for the
Rust parity test `eval/tests/perceptual_parity.rs`.

Pretrained weights are not needed (and nothing is downloaded): every parameter and batch-norm
statistic of the reference networks is set from a deterministic integer hash, and the inputs
are hash images too. The fixture stores, per network, a manifest of the tensors under their
converted (Burn) names -- produced by the same mapping functions as
tools/convert_perceptual_weights.py -- with the hash seed, offset and scale of each, plus the
reference outputs. The Rust test regenerates the tensors bit-exactly from the manifest, writes
them to a SafeTensors file and loads it through the real `Lpips::load` /
`InceptionPool3::load`, so the committed fixture stays small (VGG16 alone would be 58 MB).

Value of element `i` (flat, row-major) of a tensor with seed `s`:

    h = (i + s * 0x9E3779B97F4A7C15) mod 2^64          # splitmix64 finaliser:
    h = (h ^ (h >> 30)) * 0xBF58476D1CE4E5B9 mod 2^64
    h = (h ^ (h >> 27)) * 0x94D049BB133111EB mod 2^64
    h =  h ^ (h >> 31)
    u = (h >> 40) / 2^24                                 # exact in f32, in [0, 1)
    value = f32(offset + scale * (2u - 1))               # computed in f64

Usage (needs torch, lpips, pytorch-fid, numpy, scipy; CPU is fine, ~1 min):

    python tools/make_perceptual_fixtures.py [--out eval/tests/fixtures/perceptual/reference.json]
"""

import argparse
import json
import math
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from convert_perceptual_weights import inception_tensors, lpips_tensors  # noqa: E402

MASK = (1 << 64) - 1


def hash_uniform(n, seed):
    """u in [0, 1) for flat indices 0..n, as described in the module docstring."""
    base = np.uint64((seed * 0x9E3779B97F4A7C15) & MASK)
    with np.errstate(over="ignore"):
        h = np.arange(n, dtype=np.uint64) + base
        h = (h ^ (h >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        h = (h ^ (h >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        h = h ^ (h >> np.uint64(31))
    return (h >> np.uint64(40)).astype(np.float64) / float(1 << 24)


def hash_tensor(shape, seed, offset, scale):
    n = int(np.prod(shape)) if len(shape) else 1
    v = offset + scale * (2.0 * hash_uniform(n, seed) - 1.0)
    return v.astype(np.float32).reshape(shape)


def formula(key, shape):
    """(offset, scale) of a tensor by its converted name: He-uniform conv weights (variance
    2/fan_in) keep activations O(1) through the deep networks; batch norms near identity."""
    if key.startswith("lins."):
        return 0.1, 0.05  # LPIPS heads are non-negative
    leaf = key.rsplit(".", 1)[1]
    if leaf == "weight":
        fan_in = int(np.prod(shape[1:]))
        return 0.0, math.sqrt(6.0 / fan_in)
    return {
        "bias": (0.0, 0.05),
        "gamma": (1.0, 0.2),
        "beta": (0.0, 0.1),
        "running_mean": (0.0, 0.1),
        "running_var": (1.0, 0.3),
    }[leaf]


def fill(burn_to_torch, seed_base):
    """Sets every torch tensor from the hash; returns the manifest (sorted by key)."""
    manifest = []
    for k, key in enumerate(sorted(burn_to_torch)):
        tensor = burn_to_torch[key]
        shape = list(tensor.shape)
        offset, scale = formula(key, shape)
        seed = seed_base + k
        with torch.no_grad():
            tensor.copy_(torch.from_numpy(hash_tensor(shape, seed, offset, scale)))
        manifest.append({"key": key, "shape": shape, "seed": seed, "offset": offset, "scale": scale})
    return manifest


def image(shape, seed):
    return {"shape": list(shape), "seed": seed, "offset": 0.5, "scale": 0.5}


def image_tensor(spec):
    return torch.from_numpy(hash_tensor(spec["shape"], spec["seed"], spec["offset"], spec["scale"]))


def lpips_case(net, seed_base):
    import lpips

    # pretrained=True loads only the linear heads, from the package's own files;
    # pnet_rand=True keeps torchvision from downloading the backbone.
    model = lpips.LPIPS(net=net, version="0.1", pretrained=True, pnet_rand=True, verbose=False).eval()
    state = model.state_dict(keep_vars=True)
    named = lpips_tensors(net, state, state)
    manifest = fill(named, seed_base)
    a_spec = image([2, 3, 64, 48], seed_base + 500)
    b_spec = image([2, 3, 64, 48], seed_base + 501)
    with torch.no_grad():
        val, per_layer = model(image_tensor(a_spec), image_tensor(b_spec), retPerLayer=True, normalize=True)
    return {
        "tensors": manifest,
        "a": a_spec,
        "b": b_spec,
        "distance": val.flatten().tolist(),
        "per_layer": [r.flatten().tolist() for r in per_layer],
    }


def inception_case(seed_base):
    from pytorch_fid import inception as fi

    # Build pytorch-fid's own InceptionV3([3], use_fid_inception=True) without its download:
    # the URL loader returns nothing and the one load_state_dict call is captured instead, which
    # also hands us the torchvision-named network (`Conv2d_*`, `Mixed_*`).
    captured = {}
    original = torch.nn.Module.load_state_dict

    def capture(self, state_dict, *args, **kwargs):
        captured["inception"] = self

    fi.load_state_dict_from_url = lambda *a, **k: None
    torch.nn.Module.load_state_dict = capture
    try:
        model = fi.InceptionV3([0, 1, 2, 3], use_fid_inception=True).eval()
    finally:
        torch.nn.Module.load_state_dict = original
    named = inception_tensors(captured["inception"].state_dict(keep_vars=True))
    manifest = fill(named, seed_base)
    cases = []
    for k, shape in enumerate([[1, 3, 40, 52], [1, 3, 320, 310]]):
        spec = image(shape, seed_base + 900 + k)
        with torch.no_grad():
            blocks = model(image_tensor(spec))
        pool3 = blocks[3].flatten(1)
        cases.append({
            "images": spec,
            "features": pool3[0].tolist(),
            "block_mean_std": [[float(b.mean()), float(b.std())] for b in blocks],
        })
    return {"tensors": manifest, "cases": cases}


def fid_case(n1, n2, dim, seed):
    from pytorch_fid.fid_score import calculate_frechet_distance

    rows = []
    stats = []
    for k, n in enumerate((n1, n2)):
        spec = {"shape": [n, dim], "seed": seed + k, "offset": 0.1 * k, "scale": 1.0 + 0.5 * k}
        act = hash_tensor(spec["shape"], spec["seed"], spec["offset"], spec["scale"])
        # Correlate the columns so the covariances are not near-diagonal.
        act = (act + 0.5 * np.roll(act, 1, axis=1)).astype(np.float32)
        rows.append(act)
        # Exactly pytorch_fid.fid_score.calculate_activation_statistics on float32 activations.
        stats.append((np.mean(act, axis=0), np.cov(act, rowvar=False)))
    fid = calculate_frechet_distance(stats[0][0], stats[0][1], stats[1][0], stats[1][1])
    return {
        "dim": dim,
        "a": rows[0].flatten().tolist(),
        "b": rows[1].flatten().tolist(),
        "fid": float(fid),
    }


def main():
    p = argparse.ArgumentParser()
    here = os.path.dirname(os.path.abspath(__file__))
    p.add_argument("--out", default=os.path.join(here, "..", "eval", "tests", "fixtures", "perceptual", "reference.json"))
    args = p.parse_args()
    torch.set_num_threads(max(1, os.cpu_count() or 1))
    out = {
        "generator": "tools/make_perceptual_fixtures.py",
        "versions": {"torch": torch.__version__, "numpy": np.__version__},
        "lpips_alex": lpips_case("alex", 1000),
        "lpips_vgg": lpips_case("vgg", 2000),
        "inception": inception_case(3000),
        "fid": [fid_case(60, 45, 12, 7000), fid_case(6, 9, 16, 7100)],
    }
    try:
        import importlib.metadata as md
        out["versions"].update({p: md.version(p) for p in ("lpips", "pytorch-fid", "scipy")})
    except Exception:  # noqa: BLE001 - versions are informative only
        pass
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(out, f, separators=(",", ":"))
    print(f"wrote {args.out} ({os.path.getsize(args.out)} bytes)")
    for net in ("lpips_alex", "lpips_vgg"):
        print(net, out[net]["distance"])
    for case in out["inception"]["cases"]:
        f = np.array(case["features"])
        print("inception", case["images"]["shape"], "mean", f.mean(), "std", f.std(), case["block_mean_std"])
    print("fid", [c["fid"] for c in out["fid"]])


if __name__ == "__main__":
    main()
