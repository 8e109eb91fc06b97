"""`python -m bench run` end to end on a tiny synthetic sequence, and the pieces it is made of."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from bench.methods import ANCHORS, Method, anchor_method, pipeline_method, select
from bench.report import COLUMNS, pareto_front, sequence_table, shares_note, write_all
from bench.run import benchmark, choose_crop, unique_names
from bench.scaling import measure
from service import pipelines
from service.exr import write_frame
from service.pipelines import tiled


def test_benchmark_writes_all_four_outputs(tiny_sequence_dir: Path, tmp_path: Path) -> None:
    needs_missing_layer = Method("needs-sampleCount", "pipeline", lambda: pipelines.get("bilateral"),
                                  ("sampleCount", "roughnessX"), False)
    methods = [pipeline_method("bilateral"), needs_missing_layer, *map(anchor_method, ANCHORS)]
    results, runs = benchmark([tiny_sequence_dir], methods, flip=False, progress=False, command=["test"])
    paths = write_all(results, runs, tmp_path / "report")
    assert all(p.is_file() and p.stat().st_size > 0 for p in paths.values())

    stored = json.loads(paths["results.json"].read_text())
    assert stored["environment"]["versions"]["python"].startswith("3.")
    assert stored["environment"]["machine"]["cpu"]
    assert "OIDN_NUM_THREADS" in stored["environment"]["threads"]
    seq = stored["sequences"][0]
    assert (seq["width"], seq["height"], seq["frames"]) == (40, 24, 3)
    skipped = seq["results"]["needs-sampleCount"]
    assert skipped["status"] == "skipped" and "roughnessX" in skipped["note"]
    for name in ("bilateral", *ANCHORS):
        record = seq["results"][name]
        assert record["status"] == "ok", record.get("note")
        assert len(record["ms"]) == 3 * 3 and len(record["per_frame"]) == 3  # 3 timed passes of 3 frames
        assert record["summary"]["ms_per_frame"] > 0 and record["summary"]["rel_l2"] > 0
    noisy, oidn = seq["results"]["noisy"]["summary"], seq["results"]["oidn-high"]["summary"]
    assert oidn["rel_l2"] < noisy["rel_l2"]
    assert noisy["worst_tile"] == pytest.approx(1.0) and noisy["failing_tiles"] == 0  # the input against itself
    assert oidn["worst_tile_at"].startswith("frame ")
    overall = stored["overall"]
    assert overall["oidn-high"]["rel_l2_vs_oidn_high"] == pytest.approx(1.0)
    assert overall["needs-sampleCount"]["sequences"] == 0
    assert overall["bilateral"]["is_temporal"] is False and overall["bilateral"]["kind"] == "pipeline"

    assert overall["noisy"]["worst_tile"] == pytest.approx(1.0)

    md = paths["report.md"].read_text()
    assert "| worst tile | tiles > 1.1x |" in md
    assert "## Overall" in md and f"## {tiny_sequence_dir.name}" in md and "| bilateral |" in md
    page = paths["report.html"].read_text()
    assert page.count("<figure>") == 2 + 1 + 2  # input, bilateral, oidn-high, oidn-fast, reference
    assert paths["pareto.png"].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert paths[f"curves-{tiny_sequence_dir.name}.png"].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert f"(curves-{tiny_sequence_dir.name}.png)" in md
    assert f'src="curves-{tiny_sequence_dir.name}.png"' in page  # rendered once, beside the report


def test_sequence_without_reference_is_refused(tmp_path: Path) -> None:
    write_frame(tmp_path / "s" / "frame_0000.exr", {"color": np.ones((4, 4, 3), np.float32)})
    with pytest.raises(ValueError, match="no 'reference' layer"):
        benchmark([tmp_path / "s"], select(["none"], ["none"]), progress=False)


def test_failing_method_is_recorded_not_fatal(tiny_sequence_dir: Path) -> None:
    def broken():
        raise RuntimeError("cannot load weights")

    methods = [Method("broken", "pipeline", broken, ("color",), False), anchor_method("noisy")]
    results, _ = benchmark([tiny_sequence_dir], methods, flip=False, progress=False)
    record = results["sequences"][0]["results"]["broken"]
    assert record["status"] == "failed" and "cannot load weights" in record["note"]
    assert results["sequences"][0]["results"]["noisy"]["status"] == "ok"


def test_select_resolves_groups() -> None:
    assert [m.name for m in select(["none"], ["oidn"])] == ["noisy", "oidn-high", "oidn-fast"]
    assert [m.name for m in select(None, ["none"])] == pipelines.names()
    with pytest.raises(KeyError, match="unknown pipeline"):
        select(["nope"], None)


def test_pareto_front() -> None:
    points = {"slow-good": (100.0, 0.01), "fast-bad": (1.0, 0.3), "dominated": (200.0, 0.02), "mid": (10.0, 0.05)}
    assert pareto_front(points) == ["fast-bad", "mid", "slow-good"]


def test_crop_finds_the_detail() -> None:
    reference = np.zeros((64, 80, 3), np.float32)
    reference[40:56, 50:70] = np.indices((16, 20)).sum(axis=0)[..., None] % 2 * 5.0  # a checker patch
    y0, x0, h, w = choose_crop(reference, size=24)
    assert (h, w) == (24, 24) and y0 <= 40 < y0 + h and x0 <= 50 < x0 + w
    assert choose_crop(reference[:5, :7], size=24) == (0, 0, 5, 7)


def test_unique_names() -> None:
    assert unique_names([Path("a/x"), Path("b/x"), Path("c/y")]) == ["a/x", "b/x", "y"]


def test_scaling_measures_time_and_memory(tmp_path: Path) -> None:
    record = measure("noisy", 32, 16, 2)
    assert record["ms_per_frame"] > 0 and len(record["ms"]) == 2
    assert record["ms_per_megapixel"] == pytest.approx(record["ms_per_frame"] / (32 * 16 / 1e6))
    assert record["peak_traced_mib"] > 0



def test_a_method_may_name_pipeline_options_and_bad_ones_are_refused_up_front() -> None:
    from bench.methods import pipeline_method

    method = pipeline_method("bilateral:radius=1,sigma2_albedo=0.5")
    assert method.name == "bilateral:radius=1,sigma2_albedo=0.5" and method.kind == "pipeline"
    assert method.make().options.radius == 1
    with pytest.raises(ValueError, match="pipeline 'bilateral' has no option 'radiu'"):
        pipeline_method("bilateral:radiu=1")
    with pytest.raises(ValueError, match="radius"):
        pipeline_method("bilateral:radius=99")


def test_autos_blend_is_recorded_and_its_time_set_against_the_candidate_it_weighs_most(tiny_sequence_dir: Path) -> None:
    results, _ = benchmark([tiny_sequence_dir], [pipeline_method("auto"), pipeline_method("flr")], flip=False,
                           progress=False, command=["test"], repeats=1)
    records = results["sequences"][0]["results"]
    shares = records["auto"]["shares"]
    assert set(shares) <= set(tiled.CANDIDATES) and sum(shares.values()) == pytest.approx(1.0)
    assert list(shares.values()) == sorted(shares.values(), reverse=True)  # the largest weight first
    assert "shares" not in records["flr"]
    record = {"shares": {"kpn": 0.75, "flr": 0.25}, "summary": {"ms_per_frame": 12.0, "ms_mean": 20.0}}
    ran = {"kpn": {"status": "ok", "summary": {"ms_per_frame": 10.0, "ms_mean": 10.0}}}
    assert shares_note("auto", record, ran) == (
        "- `auto` blended (weight, mean over tiles and frames): kpn 75%, flr 25%; "
        "its median frame takes 1.20x kpn's, its mean 2.00x")
    assert shares_note("auto", record, {}).endswith("flr 25%")


def test_a_sequence_table_names_where_a_method_came_out_worse_than_its_input() -> None:
    summary = {key: None for key, _, _ in COLUMNS}
    passing = {**summary, "rel_l2": 0.02, "worst_tile": 0.9, "worst_tile_at": "frame 0 (0, 0)", "failing_tiles": 0}
    failing = {**summary, "rel_l2": 0.03, "worst_tile": 1.5, "worst_tile_at": "frame 2 (16, 32)", "failing_tiles": 3}
    table = sequence_table({"results": {"bmfr": {"status": "ok", "summary": passing},
                                        "flr": {"status": "ok", "summary": failing}}})
    assert "| 0.0300 |" in table and "| 1.50x | 3 |" in table and "| 0.90x | 0 |" in table
    notes = [line for line in table.splitlines() if line.startswith("- ")]
    assert notes == ["- `flr`: 3 tiles worse than the noisy input's by more than 10%; the worst 1.5x at "
                     "frame 2 (16, 32)"]
