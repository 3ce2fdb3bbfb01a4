#!/usr/bin/env python3
"""Writes the tiny golden weights in the release checkpoint's container format.

The release's `GAGAvatar.pt` is `torch.save({"model": state_dict, "meta_cfg": config})`, with the
perceptual-loss networks inside the state dict under `percep_loss.*` and the config an object of
the release's own dict class. This script wraps `crates/net/tests/golden/tiny_weights.safetensors`
the same way (one fake `percep_loss` tensor, a config of a custom dict class) so the Rust loader
is tested on that layout without the real file.

Regenerate:  python3 tools/reference/make_release_format_checkpoint.py
"""

import collections
import os

import torch
from safetensors.torch import load_file

ROOT = os.path.join(os.path.dirname(__file__), "..", "..")
GOLDEN = os.path.join(ROOT, "crates", "net", "tests", "golden")


class ConfigDict(dict):
    """Stands in for the release's config class: unpickling it must not need the class."""


def main():
    sd = load_file(os.path.join(GOLDEN, "tiny_weights.safetensors"))
    state = collections.OrderedDict(sorted(sd.items()))
    state["percep_loss.vggface.network.0.weight"] = torch.arange(6, dtype=torch.float32).reshape(2, 3)
    meta = ConfigDict(MODEL=ConfigDict(NAME="GAGAvatar", PRESET="tiny"), TRAIN={"LR": 1e-4, "STEPS": [1, 2]})
    out = os.path.join(GOLDEN, "tiny_release_format.pt")
    torch.save({"model": state, "meta_cfg": meta}, out)
    print(f"wrote {out} ({os.path.getsize(out)} bytes)")


if __name__ == "__main__":
    main()
