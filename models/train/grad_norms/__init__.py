"""`python -m models.train.grad_norms NET --data DIR [--init CKPT] [--windows N] [--tone-eps E]`: the gradient
norm of single training windows, to find those that would dominate a batch.

Each window is drawn as training draws them (`SequenceBank.sample`, the recipe's frames and crop, `--seed`), its
loss (the recipe's) back-propagated alone through the network (`--init`'s weights, with the `--warp` and
`--tone-eps` its run had unless `--tone-eps` is given; or a fresh network), and the global gradient norm
recorded. Printed: percentiles of the norms and losses, and the
`--top` windows of largest norm with their sequence and the share of their target pixels darker than DARK
(demodulated radiance, mean of the channels), where the loss's power is steepest.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from models.train.dataset import SequenceBank, collate
from models.train.train import RAE_ONLY, TrainOptions, init_state, make_recipe

DARK = 0.01  # demodulated radiance below which a target pixel counts as dark


@dataclass(frozen=True)
class WindowNorm:
    sequence: str  # the sequence the window was cut from
    loss: float  # the recipe's loss of the window alone
    norm: float  # the global L2 norm of its gradient
    dark: float  # share of its target pixels darker than DARK


def options_for(net: str, data: str, init: str = "", tone_eps: float | None = None) -> TrainOptions:
    """The training options the windows are measured under: `init`'s run's warp, tone eps and (rae) temporal
    weight (ValueError where `init` holds another network), `tone_eps` instead of its where given."""
    stored = torch.load(init, map_location="cpu", weights_only=False).get("options", {}) if init else {}
    if stored.get("net", net) != net:
        raise ValueError(f"{init} holds a '{stored['net']}' network, not '{net}'")
    eps = tone_eps if tone_eps is not None else stored.get("tone_eps", TrainOptions.tone_eps)
    rae_only = {"temporal_weight": stored.get("temporal_weight", RAE_ONLY["temporal_weight"])} if net == "rae" else {}
    return TrainOptions(net=net, data=data, val=data, out="", init=init, warp=bool(stored.get("warp", False)),
                        tone_eps=eps, **rae_only)


def window_norms(opts: TrainOptions, bank: SequenceBank, count: int, seed: int) -> list[WindowNorm]:
    """`count` windows' losses and gradient norms (module docstring) for `opts`' network, recipe and weights."""
    recipe = make_recipe(opts)
    net = recipe.load(init_state(opts.init)) if opts.init else recipe.build(opts.seed)
    net.train()
    rng = np.random.default_rng(seed)
    results = []
    for _ in range(count):
        index = int(rng.integers(len(bank.sequences)))
        window = bank.sample(rng, recipe.frames, recipe.crop, reverse=recipe.reverse, index=index)
        terms = recipe.loss(net, collate([window]))
        net.zero_grad(set_to_none=True)
        terms.total.backward()
        norm = torch.sqrt(sum((p.grad.double() ** 2).sum() for p in net.parameters() if p.grad is not None))
        dark = float((window.target.mean(dim=-3) < DARK).double().mean())
        results.append(WindowNorm(bank.sequences[index].name, float(terms.total.detach()), float(norm), dark))
    return results


def report(results: list[WindowNorm], top: int) -> str:
    """The printed summary (module docstring) of `results`, `top` windows listed."""
    norms, losses = np.array([r.norm for r in results]), np.array([r.loss for r in results])
    points = [50, 90, 99, 100]
    lines = [f"{len(results)} windows; percentiles {'/'.join(map(str, points))}",
             "gradient norm " + " ".join(f"{v:.4g}" for v in np.percentile(norms, points)),
             "loss          " + " ".join(f"{v:.4g}" for v in np.percentile(losses, points))]
    lines += [f"  norm {r.norm:9.4g}  loss {r.loss:.4f}  dark {100 * r.dark:3.0f}%  {r.sequence}"
              for r in sorted(results, key=lambda r: -r.norm)[:top]]
    return "\n".join(lines)
