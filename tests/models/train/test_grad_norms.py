"""`python -m models.train.grad_norms`: single windows' gradient norms, as training draws and scores them."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from models.data import SAMPLE_DIRS  # noqa: E402
from models.train.dataset import SequenceBank, collate, load_sequence  # noqa: E402
from models.train.grad_norms import options_for, report, window_norms  # noqa: E402
from models.train.grad_norms.__main__ import main  # noqa: E402
from models.train.train import BEST, TrainOptions, make_recipe, train  # noqa: E402

SAMPLE = SAMPLE_DIRS[0]


def test_each_norm_is_the_gradient_of_that_window_alone():
    bank = SequenceBank([load_sequence(SAMPLE)])
    opts = TrainOptions(net="flnr", data=str(SAMPLE), val=str(SAMPLE), out="")
    results = window_norms(opts, bank, 3, seed=4)
    assert [r.sequence for r in results] == [SAMPLE.name] * 3
    # the second window again, by hand: drawn after the first from the same seed
    recipe = make_recipe(opts)
    net = recipe.build(opts.seed)
    rng = np.random.default_rng(4)
    for _ in range(2):
        index = int(rng.integers(1))
        window = bank.sample(rng, recipe.frames, recipe.crop, reverse=recipe.reverse, index=index)
    terms = recipe.loss(net, collate([window]))
    terms.total.backward()
    norm = float(torch.sqrt(sum((p.grad.double() ** 2).sum() for p in net.parameters())))
    assert results[1].norm == pytest.approx(norm, rel=1e-6)
    assert results[1].loss == pytest.approx(float(terms.total.detach()))
    assert 0 <= results[1].dark <= 1 and results[0].norm != results[1].norm
    text = report(results, top=2)
    assert text.splitlines()[0] == "3 windows; percentiles 50/90/99/100" and len(text.splitlines()) == 5


def test_the_command_line_refuses_bad_options(capsys):
    with pytest.raises(SystemExit, match="tone_eps must be in"):
        main(["rae", "--data", str(SAMPLE), "--tone-eps", "0"])
    for option, value in (("--windows", "0"), ("--top", "-1"), ("--threads", "-1")):
        with pytest.raises(SystemExit, match="--windows must be >= 1, --top and --threads >= 0"):
            main(["rae", "--data", str(SAMPLE), option, value])


def test_windows_are_measured_as_the_checkpoints_run_trained(tmp_path):
    opts = TrainOptions(net="rae", data=str(SAMPLE), val=str(SAMPLE), out=str(tmp_path / "run"), steps=1, batch=1,
                        threads=1, warp=True, tone_eps=0.02)
    train(opts, progress=False)
    measured = options_for("rae", str(SAMPLE), str(tmp_path / "run" / BEST))
    assert measured.warp and measured.tone_eps == 0.02 and make_recipe(measured).reverse is False
    assert options_for("rae", str(SAMPLE), str(tmp_path / "run" / BEST), 0.05).tone_eps == 0.05
    assert not options_for("rae", str(SAMPLE)).warp
    with pytest.raises(ValueError, match="holds a 'rae' network, not 'kpn'"):
        options_for("kpn", str(SAMPLE), str(tmp_path / "run" / BEST))
