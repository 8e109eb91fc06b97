"""One module per network (shared ARCHITECTURE.md)."""

from collections.abc import Callable
from dataclasses import asdict
from typing import Any, TypeVar

import torch
from torch import nn

Net = TypeVar("Net", bound=nn.Module)


def count_parameters(net: nn.Module) -> int:
    """The number of scalar weights of `net`."""
    return sum(p.numel() for p in net.parameters())


def seeded(make: Callable[[], Net], seed: int | None) -> Net:
    """make() with torch's generator seeded by `seed` in a forked RNG state (the global state untouched);
    seed None: make() on the global generator."""
    if seed is None:
        return make()
    with torch.random.fork_rng():
        torch.manual_seed(seed)
        return make()


def state_for(net: nn.Module) -> dict:
    """{'config': constructor args (the network's `config` dataclass), 'state_dict': weights}: what a checkpoint
    stores of a network."""
    return {"config": asdict(net.config), "state_dict": net.state_dict()}


def from_checkpoint(network: Callable[[Any], Net], config: Callable[..., Any], ckpt: dict) -> Net:
    """network(config(...)) of a checkpoint dict (`state_for` keys): the constructor args as stored (JSON lists
    back to tuples), the weights loaded, in eval mode."""
    values = {k: tuple(v) if isinstance(v, list) else v for k, v in ckpt["config"].items()}
    net = network(config(**values))
    net.load_state_dict(ckpt["state_dict"])
    return net.eval()
