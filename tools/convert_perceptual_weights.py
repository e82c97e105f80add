#!/usr/bin/env python3
"""Convert the standard LPIPS and FID weight files into the SafeTensors files that
`lifegom_eval::perceptual` loads (LPIPS v0.1 alex/vgg, pytorch-fid Inception pool3).

Nothing is downloaded: bring the original files yourself.

Inputs (each group is optional; convert what you have):

- torchvision AlexNet   `alexnet-owt-7be5be79.pth`  (--alexnet)
- torchvision VGG16     `vgg16-397923af.pth`        (--vgg16)
- lpips v0.1 heads      `alex.pth`, `vgg.pth`        (--lpips-heads DIR; default: the
  `weights/v0.1` folder of the installed `lpips` pip package, which ships them)
- pytorch-fid Inception `pt_inception-2015-12-05-6726825d.pth` (--inception)

Outputs in --out (default `weights/`, which `PerceptualModels::default_dir` uses unless
$LIFEGOM_WEIGHTS is set):

- `lpips_alex.safetensors`   (AlexNet backbone + alex heads)
- `lpips_vgg.safetensors`    (VGG16 backbone + vgg heads)
- `pt_inception.safetensors` (FID Inception, `fc.*` dropped)

Usage:

    python -m venv /tmp/venv && /tmp/venv/bin/pip install torch safetensors lpips
    /tmp/venv/bin/python tools/convert_perceptual_weights.py \\
        --alexnet ~/.cache/torch/hub/checkpoints/alexnet-owt-7be5be79.pth \\
        --vgg16 ~/.cache/torch/hub/checkpoints/vgg16-397923af.pth \\
        --inception ~/.cache/torch/hub/checkpoints/pt_inception-2015-12-05-6726825d.pth \\
        --out weights/

(`~/.cache/torch/hub/checkpoints/` is where torchvision / pytorch-fid put them after one
online run of `lpips.LPIPS(net=...)` and `python -m pytorch_fid`.)

Key names. The files hold float32 tensors named exactly like the Burn module fields, with
PyTorch layouts (conv weights `[out, in, kh, kw]`), so the Rust loader needs no remapping:

- LPIPS: torchvision `features.{i}.{weight,bias}` -> `convs.{j}.{weight,bias}` where `j` is
  the position of conv `i` in the backbone (alex: i = 0, 3, 6, 8, 10; vgg: 0, 2, 5, 7, 10, 12,
  14, 17, 19, 21, 24, 26, 28; later layers are unused by LPIPS and dropped); the lpips
  package's `lin{k}.model.1.weight` -> `lins.{k}.weight`. The LPIPS module's own names
  `net.slice{s}.{i}.*` are accepted in place of `features.{i}.*`.
- Inception: `Conv2d_*` / `Mixed_*` prefixes lower-cased (`conv2d_1a_3x3`, `mixed_5b`),
  BatchNorm `weight`/`bias` -> `gamma`/`beta` (Burn's names), `running_mean`/`running_var`
  kept, `num_batches_tracked` and the classifier `fc.*` dropped.

The same mapping functions are used by tools/make_perceptual_fixtures.py, whose Rust parity
test loads files with these names through the real loader.
"""

import argparse
import os
import re
import sys

ALEX_CONVS = [0, 3, 6, 8, 10]
VGG_CONVS = [0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28]
# Tensors per converted file, checked before writing.
EXPECTED_COUNTS = {"alex": 2 * 5 + 5, "vgg": 2 * 13 + 5, "inception": 94 * 5}

_BACKBONE_KEY = re.compile(r"^(?:features|net\.slice[1-5])\.(\d+)\.(weight|bias)$")
_HEAD_KEY = re.compile(r"^lin([0-4])\.model\.1\.weight$")


def lpips_tensors(net, backbone_state, heads_state):
    """Burn-named tensors of an LPIPS network.

    `backbone_state`: torchvision `alexnet()`/`vgg16()` state dict (`features.{i}.*`) or an
    `lpips.LPIPS` state dict (`net.slice{s}.{i}.*`); `heads_state`: the lpips package's
    `{alex,vgg}.pth` (`lin{k}.model.1.weight`) or an `lpips.LPIPS` state dict.
    """
    indices = ALEX_CONVS if net == "alex" else VGG_CONVS
    position = {i: j for j, i in enumerate(indices)}
    out = {}
    for key, value in backbone_state.items():
        m = _BACKBONE_KEY.match(key)
        if m and int(m.group(1)) in position:
            out[f"convs.{position[int(m.group(1))]}.{m.group(2)}"] = value
    for key, value in heads_state.items():
        m = _HEAD_KEY.match(key)
        if m:
            out[f"lins.{m.group(1)}.weight"] = value
    return out


def inception_tensors(state):
    """Burn-named tensors of pytorch-fid's FID Inception (its state dict, as in
    `pt_inception-2015-12-05-6726825d.pth` or `fid_inception_v3().state_dict()`)."""
    out = {}
    for key, value in state.items():
        if key.startswith("fc.") or key.endswith("num_batches_tracked"):
            continue
        m = re.match(r"^(Conv2d_\w+?|Mixed_\w+?)\.(.+)$", key)
        if not m:
            raise ValueError(f"unexpected Inception key {key!r}")
        rest = m.group(2)
        rest = re.sub(r"\.bn\.weight$", ".bn.gamma", rest)
        rest = re.sub(r"\.bn\.bias$", ".bn.beta", rest)
        rest = re.sub(r"^bn\.weight$", "bn.gamma", rest)
        rest = re.sub(r"^bn\.bias$", "bn.beta", rest)
        out[f"{m.group(1).lower()}.{rest}"] = value
    return out


def _check(what, tensors):
    expected = EXPECTED_COUNTS[what]
    if len(tensors) != expected:
        raise SystemExit(
            f"{what}: {len(tensors)} tensors after conversion, expected {expected}; "
            f"is this the right file? keys: {sorted(tensors)[:8]}..."
        )


def _save(tensors, path):
    import torch
    from safetensors.torch import save_file

    contiguous = {k: v.detach().to(torch.float32).contiguous() for k, v in tensors.items()}
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    save_file(contiguous, path)
    print(f"wrote {path} ({len(contiguous)} tensors)")


def _load(path):
    import torch

    state = torch.load(path, map_location="cpu", weights_only=True)
    if isinstance(state, dict) and "state_dict" in state:
        state = state["state_dict"]
    return state


def default_heads_dir():
    try:
        import lpips
    except ImportError:
        return None
    return os.path.join(os.path.dirname(lpips.__file__), "weights", "v0.1")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--alexnet", help="torchvision alexnet-owt-7be5be79.pth")
    p.add_argument("--vgg16", help="torchvision vgg16-397923af.pth")
    p.add_argument("--lpips-heads", default=default_heads_dir(),
                   help="folder with the lpips v0.1 alex.pth / vgg.pth (default: the lpips package's)")
    p.add_argument("--inception", help="pytorch-fid pt_inception-2015-12-05-6726825d.pth")
    p.add_argument("--out", default="weights", help="output folder (default: weights/)")
    args = p.parse_args(argv)
    if not (args.alexnet or args.vgg16 or args.inception):
        p.error("nothing to convert: give --alexnet, --vgg16 and/or --inception")

    for net, backbone in (("alex", args.alexnet), ("vgg", args.vgg16)):
        if not backbone:
            continue
        if not args.lpips_heads:
            raise SystemExit("--lpips-heads not given and the lpips package is not installed")
        heads = _load(os.path.join(args.lpips_heads, f"{net}.pth"))
        tensors = lpips_tensors(net, _load(backbone), heads)
        _check(net, tensors)
        _save(tensors, os.path.join(args.out, f"lpips_{net}.safetensors"))
    if args.inception:
        tensors = inception_tensors(_load(args.inception))
        _check("inception", tensors)
        _save(tensors, os.path.join(args.out, "pt_inception.safetensors"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
