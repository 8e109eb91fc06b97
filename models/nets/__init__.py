"""One module per network (shared ARCHITECTURE.md)."""

from torch import nn


def count_parameters(net: nn.Module) -> int:
    """The number of scalar weights of `net`."""
    return sum(p.numel() for p in net.parameters())
