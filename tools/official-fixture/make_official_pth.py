#!/usr/bin/env python3
"""Writes an official-format LIFe-GoM training checkpoint with real `torch.save`.

The official trainer saves `{"iter": step, "network": net.state_dict(), "optimizer":
optimizer.state_dict()}`. This script builds exactly that structure from a state dict in
SafeTensors (as `lifegom-train --export X.safetensors --from MODEL` writes it: official key
names, PyTorch layouts) and adds what a real PyTorch state dict carries beside the weights:
every BatchNorm's `num_batches_tracked` buffer (int64 scalars) and the image encoder's
`mean`/`std` normalisation buffers. The optimizer entry is a real `torch.optim.Adam` state
dict over those parameters, before any step (its `state` is empty, which keeps the file small).

Used to make tests/fixtures/official/demo-v2.pth (see that folder's README):

    lifegom-train --export /tmp/demo.safetensors --from assets/demo/demo.lgck
    /usr/bin/python3 tools/official-fixture/make_official_pth.py \
        /tmp/demo.safetensors tests/fixtures/official/demo-v2.pth --iter 19250

Needs PyTorch (Debian: `apt install python3-torch`); nothing else.
"""

import argparse
import collections
import json
import struct

import torch


def read_safetensors(path):
    """A minimal SafeTensors reader (F32 only): header length, JSON header, raw data."""
    with open(path, "rb") as f:
        blob = f.read()
    (n,) = struct.unpack("<Q", blob[:8])
    header = json.loads(blob[8 : 8 + n])
    data = blob[8 + n :]
    tensors = collections.OrderedDict()
    for name, info in header.items():
        if name == "__metadata__":
            continue
        if info["dtype"] != "F32":
            raise SystemExit(f"{path}: `{name}` is {info['dtype']}, only F32 is expected")
        start, end = info["data_offsets"]
        flat = torch.frombuffer(bytearray(data[start:end]), dtype=torch.float32)
        tensors[name] = flat.reshape(info["shape"]).clone()
    return tensors


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("state_dict", help="official-named SafeTensors file")
    parser.add_argument("out", help="checkpoint to write (.pth)")
    parser.add_argument("--iter", type=int, default=0, help="training step to record")
    parser.add_argument(
        "--legacy",
        action="store_true",
        help="write the pre-1.6 pickle container instead of the zip archive",
    )
    args = parser.parse_args()

    weights = read_safetensors(args.state_dict)
    network = collections.OrderedDict()
    # The encoder's normalisation buffers come first in the official module.
    network["img_encoder.mean"] = torch.tensor([0.485, 0.456, 0.406]).reshape(1, 3, 1, 1)
    network["img_encoder.std"] = torch.tensor([0.229, 0.224, 0.225]).reshape(1, 3, 1, 1)
    for name, tensor in weights.items():
        network[name] = tensor
        if name.endswith(".running_var"):
            prefix = name[: -len("running_var")]
            network[prefix + "num_batches_tracked"] = torch.tensor(0, dtype=torch.int64)

    params = [
        torch.nn.Parameter(t.clone())
        for name, t in network.items()
        if t.is_floating_point() and not name.endswith(("running_mean", "running_var"))
        and name not in ("img_encoder.mean", "img_encoder.std")
    ]
    optimizer = torch.optim.Adam(params, lr=5e-4)
    checkpoint = {
        "iter": args.iter,
        "network": network,
        "optimizer": optimizer.state_dict(),
    }
    torch.save(checkpoint, args.out, _use_new_zipfile_serialization=not args.legacy)
    print(
        f"{args.out}: {len(network)} state-dict entries "
        f"({len(weights)} weights), {len(params)} optimizer parameters, "
        f"torch {torch.__version__}, {'legacy' if args.legacy else 'zip'} container"
    )


if __name__ == "__main__":
    main()
