"""The outputs of `python -m bench run`: results.json, report.md, pareto.png, report.html, curves-NAME.png.

report.md holds one table per sequence and the overall table; pareto.png plots ms per megapixel
against relL2 (log-log) with the Pareto front; report.html shows, per sequence, one crop of the last
frame for the input, every method and the reference side by side, and the per-frame error curves.
"""

from __future__ import annotations

import base64
import html
import io
import json
from pathlib import Path
from typing import Any

import matplotlib
import matplotlib.ticker

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (the backend must be chosen first)
import numpy as np  # noqa: E402

from bench.methods import ANCHORS  # noqa: E402
from bench.run import SequenceRun  # noqa: E402
from service.preview import encode_png, tonemap  # noqa: E402

# Columns of every table: (key in a summary / overall row, header, format).
COLUMNS = (
    ("ms_per_frame", "ms/frame", "{:.1f}"),
    ("ms_per_megapixel", "ms/MP", "{:.0f}"),
    ("rel_l2", "relL2", "{:.4f}"),
    ("dssim", "1-SSIM", "{:.4f}"),
    ("flip", "FLIP", "{:.4f}"),
    ("temporal", "temporal", "{:.4f}"),
    ("disoccluded_rel_l2", "relL2 disocc.", "{:.4f}"),
    ("worst_tile", "worst tile", "{:.2f}x"),
    ("failing_tiles", "tiles > 1.1x", "{:d}"),
)
CROP_DISPLAY_PX = 192  # on-screen size of each crop in report.html (nearest-neighbour upscaled)


def _fmt(value: Any, pattern: str) -> str:
    return "–" if value is None else pattern.format(value)


def write_all(results: dict[str, Any], runs: list[SequenceRun], out: Path) -> dict[str, Path]:
    """Write the four outputs and each sequence's per-frame error curves (curves-NAME.png, also in report.html and
    report.md) into `out` (created); returns their paths by name."""
    out.mkdir(parents=True, exist_ok=True)
    paths = {
        "results.json": out / "results.json",
        "report.md": out / "report.md",
        "pareto.png": out / "pareto.png",
        "report.html": out / "report.html",
    }
    paths["results.json"].write_text(json.dumps(results, indent=1, allow_nan=False))
    paths["report.md"].write_text(markdown(results))
    pareto_plot(results["overall"], paths["pareto.png"], subtitle=_subtitle(results))
    paths["report.html"].write_text(html_report(results, runs))
    for seq in results["sequences"]:
        paths[f"curves-{seq['name']}.png"] = out / f"curves-{seq['name']}.png"
        paths[f"curves-{seq['name']}.png"].write_bytes(_curves_png(seq))
    return paths


def _subtitle(results: dict[str, Any]) -> str:
    env = results["environment"]
    seqs = ", ".join(s["name"] for s in results["sequences"])
    return f"{env['machine']['cpu']}, {env['threads'].get('OMP_NUM_THREADS')} threads; sequences: {seqs}"


# ----------------------------------------------------------------------------------------------- markdown


def overall_table(overall: dict[str, dict[str, Any]]) -> str:
    """The overall table as markdown: one row per method, fastest first."""
    head = ("| method | kind | seqs | ms/MP | relL2 | 1-SSIM | FLIP | temporal | relL2 disocc. | worst tile | "
            "tiles > 1.1x | relL2 / OIDN-high |")
    lines = [head, "|" + "---|" * 12]
    rows = sorted(overall.items(), key=lambda kv: (kv[1]["ms_per_megapixel"] is None, kv[1]["ms_per_megapixel"]))
    for name, row in rows:
        kind = row["kind"] + (", temporal" if row["is_temporal"] else "")
        lines.append(
            f"| {name} | {kind} | {row['sequences']}/{row['of']} | {_fmt(row['ms_per_megapixel'], '{:.0f}')} | "
            f"{_fmt(row['rel_l2'], '{:.4f}')} | {_fmt(row['dssim'], '{:.4f}')} | {_fmt(row['flip'], '{:.4f}')} | "
            f"{_fmt(row['temporal'], '{:.4f}')} | {_fmt(row['disoccluded_rel_l2'], '{:.4f}')} | "
            f"{_fmt(row['worst_tile'], '{:.2f}x')} | {_fmt(row['failing_tiles'], '{:d}')} | "
            f"{_fmt(row['rel_l2_vs_oidn_high'], '{:.2f}x')} |"
        )
    return "\n".join(lines)


def sequence_table(seq: dict[str, Any]) -> str:
    lines = ["| method | " + " | ".join(h for _, h, _ in COLUMNS) + " |", "|" + "---|" * (len(COLUMNS) + 1)]
    notes = []
    for name, record in seq["results"].items():
        if record["status"] != "ok":
            lines.append(f"| {name} | " + " | ".join(record["status"] for _ in COLUMNS) + " |")
            notes.append(f"- `{name}` {record['status']}: {record['note']}")
            continue
        summary = record["summary"]
        lines.append(f"| {name} | " + " | ".join(_fmt(summary[k], f) for k, _, f in COLUMNS) + " |")
        if summary["failing_tiles"]:
            notes.append(f"- `{name}`: {summary['failing_tiles']} tiles worse than the noisy input's by more than "
                         f"10%; the worst {summary['worst_tile']:.3g}x at {summary['worst_tile_at']}")
        if "shares" in record:
            notes.append(shares_note(name, record, seq["results"]))
    return "\n".join(lines + ([""] + notes if notes else []))


def shares_note(name: str, record: dict[str, Any], results: dict[str, dict[str, Any]]) -> str:
    """One line on what `auto` (`name`) ran: each candidate's blend weight (mean over tiles and frames), and its
    time per frame against that of the one of largest weight, where that one ran in the same benchmark: the median
    frame's (which leaves the evaluation frames out while they are fewer than half) and the mean's."""
    shares = ", ".join(f"{k} {100 * v:.0f}%" for k, v in record["shares"].items())
    line = f"- `{name}` blended (weight, mean over tiles and frames): {shares}"
    most = next(iter(record["shares"]))
    if results.get(most, {}).get("status") == "ok":
        mine, theirs = record["summary"], results[most]["summary"]
        line += (f"; its median frame takes {mine['ms_per_frame'] / theirs['ms_per_frame']:.2f}x {most}'s, "
                 f"its mean {mine['ms_mean'] / theirs['ms_mean']:.2f}x")
    return line


def markdown(results: dict[str, Any]) -> str:
    env = results["environment"]
    versions = ", ".join(f"{k} {v}" for k, v in env["versions"].items() if v)
    threads = ", ".join(f"{k}={v}" for k, v in env["threads"].items() if v is not None)
    parts = [
        "# Benchmark: speed against error",
        "",
        f"Created {results['created']} in {results['wall_seconds']:.0f} s by `{' '.join(results['command'] or [])}`.",
        "",
        f"- Machine: {env['machine']['cpu']}, {env['machine']['usable_cpus']} usable CPUs, "
        f"load average {env['machine']['load_average_1m']:.1f} at the start, "
        f"{env['machine'].get('load_average_1m_end', float('nan')):.1f} at the end (other work skews timings)",
        f"- Threads: {threads}",
        f"- Versions: {versions}",
        f"- Timing: {results['settings']['ms_per_frame']}; warm-up: {results['settings']['warmup']}.",
        "- relL2: mean over frames, 0.1% of worst pixels trimmed; 1-SSIM and FLIP: mean over frames; temporal: "
        "relL2 of the frame-to-frame change against the reference's change; relL2 disocc.: untrimmed relL2 over "
        "disoccluded pixels (the reprojection marks them invalid, or motionDual differs from motion by more than "
        "0.5 px), every frame but the first; worst tile: over frames and 16x16 tiles, the largest ratio of the "
        "tile's untrimmed relL2 to the noisy input's (each plus 1e-3), the hard cases' criterion; tiles > 1.1x: "
        "(frame, tile) pairs above 1.1x, which that criterion fails.",
        "",
        "## Overall",
        "",
        f"{results['settings']['overall']}.",
        "",
        overall_table(results["overall"]),
        "",
        "![pareto](pareto.png)",
        "",
    ]
    for seq in results["sequences"]:
        parts += [
            f"## {seq['name']}",
            "",
            f"{seq['width']}x{seq['height']}, {seq['frames']} frames, `{seq['path']}`",
            "",
            sequence_table(seq),
            "",
            f"![per-frame errors](curves-{seq['name']}.png)",
            "",
        ]
    return "\n".join(parts)


# ----------------------------------------------------------------------------------------------- pareto


def pareto_front(points: dict[str, tuple[float, float]]) -> list[str]:
    """Names of the points no other point beats in both coordinates (lower is better in each), by x."""
    front, best_y = [], np.inf
    for name, (_, y) in sorted(points.items(), key=lambda kv: (kv[1][0], kv[1][1])):
        if y < best_y:
            front.append(name)
            best_y = y
    return front


def _label_points(ax: Any, points: dict[str, tuple[float, float]], fontsize: float = 8.5) -> None:
    """Label every point, trying four positions around it and taking the first whose text box (estimated
    from the name's length) overlaps no label placed before."""
    ax.autoscale_view()
    placed: list[tuple[float, float, float, float]] = []  # display-space boxes (x0, y0, x1, y1)
    char_w, height = 0.6 * fontsize, fontsize  # points; a rough width of one character
    scale = ax.figure.dpi / 72.0
    for name, (x, y) in sorted(points.items(), key=lambda kv: kv[1]):
        px, py = ax.transData.transform((x, y))
        width = char_w * len(name)
        box = None
        for dx, dy, ha in ((6, 4, "left"), (6, -13, "left"), (-6, 4, "right"), (-6, -13, "right")):
            x0 = px + scale * (dx if ha == "left" else dx - width)
            candidate = (x0, py + scale * dy, x0 + scale * width, py + scale * (dy + height))
            if not any(c[0] < b[2] and b[0] < c[2] and c[1] < b[3] and b[1] < c[3]
                       for b in placed for c in (candidate,)):
                box = (dx, dy, ha, candidate)
                break
        dx, dy, ha, candidate = box or (6, 4, "left", (px, py, px, py))
        placed.append(candidate)
        ax.annotate(name, (x, y), textcoords="offset points", xytext=(dx, dy), ha=ha, fontsize=fontsize)


def pareto_plot(overall: dict[str, dict[str, Any]], path: Path, *, subtitle: str = "") -> None:
    """ms per megapixel against relL2, log-log, one labelled point per method, Pareto front drawn."""
    points = {
        name: (row["ms_per_megapixel"], row["rel_l2"])
        for name, row in overall.items()
        if row["ms_per_megapixel"] and row["rel_l2"]
    }
    fig, ax = plt.subplots(figsize=(7.5, 5.0), dpi=110)
    front = pareto_front(points)
    own_front = pareto_front({n: p for n, p in points.items() if overall[n]["kind"] == "pipeline"})
    for names, label, colour in ((front, "Pareto front", "0.6"), (own_front, "Pareto front of the pipelines",
                                                                   "tab:blue")):
        if len(names) > 1 and (names is front or names != front):
            xs, ys = zip(*(points[n] for n in names), strict=True)
            ax.step(xs, ys, where="post", color=colour, alpha=0.6, linestyle="--", linewidth=1.2, label=label,
                    zorder=1)
    for name, (x, y) in points.items():
        anchor = overall[name]["kind"] == "anchor"
        ax.scatter([x], [y], s=46, zorder=3, marker="s" if anchor else "o",
                   color="tab:orange" if anchor else "tab:blue", edgecolor="black" if name in front else "none")
    ax.set_xscale("log")
    ax.set_yscale("log")
    _label_points(ax, points)
    ax.set_xlabel("ms per megapixel (median per frame, lower is faster)")
    ax.set_ylabel("relL2 (mean over sequences, lower is better)")
    ax.set_title("Speed against error" + (f"\n{subtitle}" if subtitle else ""), fontsize=9)
    ax.scatter([], [], marker="o", color="tab:blue", label="pipeline")
    ax.scatter([], [], marker="s", color="tab:orange", label="anchor")
    ax.legend(fontsize=8, loc="best")
    ax.grid(True, which="both", alpha=0.25)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


# ----------------------------------------------------------------------------------------------- html


def _png_uri(data: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(data).decode("ascii")


def _crop_exposure(reference: np.ndarray) -> float:
    """Exposure that maps the reference crop's mean luminance to 1 (x / (1 + x) = 0.5)."""
    mean = float(np.mean(np.maximum(reference, 0.0)))
    return 1.0 / mean if mean > 1e-8 else 1.0


def _curves_png(seq: dict[str, Any]) -> bytes:
    """Per-frame relL2 and temporal error of every method that ran on the sequence."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.4), dpi=100)
    palette = plt.get_cmap("tab20").colors
    for index, (name, record) in enumerate(seq["results"].items()):
        if record["status"] != "ok":
            continue
        frames = record["per_frame"]
        style = {"linestyle": "--" if name in ANCHORS else "-", "marker": ".", "label": name,
                 "color": palette[(2 * index) % 20 + (2 * index) // 20 % 2]}
        axes[0].plot([f["rel_l2"] for f in frames], **style)
        temporal = [(i, f["temporal"]) for i, f in enumerate(frames) if f["temporal"] is not None]
        if temporal:
            axes[1].plot(*zip(*temporal, strict=True), **style)
    for ax, title in zip(axes, ("relL2 per frame", "temporal error per frame"), strict=True):
        ax.set_yscale("log")
        ax.xaxis.set_major_locator(matplotlib.ticker.MaxNLocator(integer=True))
        ax.set_xlabel("frame")
        ax.set_title(title, fontsize=9)
        ax.grid(True, which="both", alpha=0.25)
    axes[0].legend(fontsize=7, ncol=2)
    fig.tight_layout()
    sink = io.BytesIO()
    fig.savefig(sink, format="png")
    plt.close(fig)
    return sink.getvalue()


def _figure(label: str, image: np.ndarray, exposure: float, caption: str) -> str:
    uri = _png_uri(encode_png(tonemap(image, exposure)))
    return (
        f'<figure><img src="{uri}" width="{CROP_DISPLAY_PX}" height="{CROP_DISPLAY_PX}" alt="{html.escape(label)}">'
        f"<figcaption><b>{html.escape(label)}</b><br>{html.escape(caption)}</figcaption></figure>"
    )


def html_report(results: dict[str, Any], runs: list[SequenceRun]) -> str:
    by_name = {r.sequence.name: r for r in runs}
    body = [
        "<h1>Benchmark: speed against error</h1>",
        f"<p>{html.escape(_subtitle(results))}. Created {html.escape(results['created'])}.</p>",
        "<h2>Overall</h2>",
        _table_html(overall_table(results["overall"])),
        '<img src="pareto.png" alt="Pareto plot" style="max-width:720px">',
    ]
    for seq in results["sequences"]:
        run = by_name[seq["name"]]
        crop = seq["crop"]
        exposure = _crop_exposure(run.crops["reference"])
        figures = [_figure("input (noisy)", run.crops["input"], exposure, "")]
        for name, record in seq["results"].items():
            if name in run.crops and name != "noisy":
                s = record["summary"]
                figures.append(_figure(name, run.crops[name], exposure,
                                       f"relL2 {_fmt(s['rel_l2'], '{:.4f}')}, {_fmt(s['ms_per_frame'], '{:.0f}')} ms"))
        figures.append(_figure("reference", run.crops["reference"], exposure, ""))
        body += [
            f"<h2>{html.escape(seq['name'])}</h2>",
            f"<p>{seq['width']}x{seq['height']}, {seq['frames']} frames. Crop of frame {crop['frame']}: "
            f"x {crop['x0']}..{crop['x0'] + crop['width']}, y {crop['y0']}..{crop['y0'] + crop['height']} "
            f"(the window with the most detail in the reference), exposure {exposure:.3g}.</p>",
            '<div class="crops">' + "".join(figures) + "</div>",
            _table_html(sequence_table(seq)),
            f'<img src="curves-{html.escape(seq["name"])}.png" alt="per-frame errors" style="max-width:1000px">',
        ]
    style = (
        "body{font-family:sans-serif;margin:1.5em;max-width:1400px}"
        "table{border-collapse:collapse;font-size:13px;margin:0.6em 0}"
        "td,th{border:1px solid #ccc;padding:3px 7px;text-align:right}td:first-child{text-align:left}"
        ".crops{display:flex;flex-wrap:wrap;gap:8px}figure{margin:0;font-size:12px;text-align:center}"
        "img{image-rendering:pixelated}"
    )
    return (
        "<!doctype html><html><head><meta charset='utf-8'><title>mcdenoise benchmark</title>"
        f"<style>{style}</style></head><body>" + "\n".join(body) + "</body></html>\n"
    )


def _table_html(table_md: str) -> str:
    """A markdown table (as written by this module) as an HTML table; trailing note lines as a list."""
    lines = table_md.splitlines()
    rows = [line for line in lines if line.startswith("|") and not line.startswith("|---")]
    notes = [line[2:] for line in lines if line.startswith("- ")]
    cells = [[html.escape(c.strip()) for c in row.strip("|").split("|")] for row in rows]
    out = ["<table>", "<tr>" + "".join(f"<th>{c}</th>" for c in cells[0]) + "</tr>"]
    out += ["<tr>" + "".join(f"<td>{c}</td>" for c in row) + "</tr>" for row in cells[1:]]
    out.append("</table>")
    if notes:
        out.append("<ul>" + "".join(f"<li>{html.escape(n)}</li>" for n in notes) + "</ul>")
    return "\n".join(out)

