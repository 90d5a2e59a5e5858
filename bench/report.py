"""Write docs/benchmarks.md and its plots from the benchmark result files.

Reads (each optional; a missing one is reported as not run):
  docs/benchmarks/model.json      bench/bench_model.py     ORT vs eager torch per batch and N
  docs/benchmarks/profile.json    bench/profile_model.py   ORT kernel time by block and operator
  docs/benchmarks/calls.json      bench/bench_calls.py     one 2-thread model call vs two 1-thread calls at once
  docs/benchmarks/service.json    bench/bench_service.py   pairs/s and latency by clients, batching, payload
  docs/benchmarks/scaling.json    bench/bench_scaling.py   16 clients vs 1 in interleaved windows
  docs/benchmarks/overload.json   bench/bench_overload.py  2x capacity for 60 s, SIGTERM under load
  docs/benchmarks/machine.json    bench/machine_check.py   how much of its 2 CPUs the machine gave
  docs/evaluation/evaluation.json python -m model.training.evaluate   accuracy of IFNet and Open3D baselines

    python bench/report.py
    python bench/report.py --results docs/benchmarks --evaluation docs/evaluation/evaluation.json

Every number in the report comes from those files; the goals are checked against them here.
"""

import argparse
import functools
import json
import math
import sys
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from model.artifacts import file_sha256  # noqa: E402

SHIPPED_MODEL = ROOT / "service" / "models" / "ifnet.onnx"

GOAL_P50_MS = 100.0
GOAL_ORT_SPEEDUP = 2.0
GOAL_SCALING = 1.5
GOAL_RSS_MB = 1024.0
# Model time per pair differing more than this between two rows of one batching mode means the
# machine's speed changed between them (docs/benchmarks.md, "The machine during the runs").
MACHINE_DRIFT = 1.2


MODE_STYLES = {"off": "s--", "on": "o-", "1call": "^-."}


def mode_label(cell: dict) -> str:
    """A service row's settings, e.g. "off (max 1, 2 calls)" or "1call (max 1)"."""
    calls = cell.get("model_calls", 1)
    return f"{cell['mode']} (max {cell['max_batch_size']}" + (f", {calls} calls)" if calls > 1 else ")")


def load(path: Path) -> dict | None:
    return json.loads(path.read_text()) if path.is_file() else None


def fmt(value, digits: int = 0, unit: str = "") -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    return f"{value:,.{digits}f}{unit}"


def statuses(counts: dict[str, int]) -> str:
    return ", ".join(f"{key}: {value}" for key, value in counts.items()) or "-"


def verdict(value: float | None, goal: float, lower_is_better: bool) -> str:
    if value is None:
        return "not measured"
    if (value <= goal) if lower_is_better else (value >= goal):
        return "met"
    if lower_is_better:
        return f"missed: {value / goal:.2f}x the limit ({value - goal:,.0f} over)"
    return f"missed: {value:.4g} is {value / goal:.1%} of the goal"


# ---------------------------------------------------------------- plots


def plot_model(rows: list[dict], path: Path) -> None:
    import matplotlib.pyplot as plt

    labels = [f"B={r['batch']}\nN={r['points']}" for r in rows]
    x = range(len(rows))
    fig, ax = plt.subplots(figsize=(7, 3.5))
    ax.bar([i - 0.2 for i in x], [r["ort_ms_per_pair"] for r in rows], 0.4, label="ONNX Runtime")
    ax.bar([i + 0.2 for i in x], [r["eager_ms_per_pair"] for r in rows], 0.4, label="eager torch")
    ax.set_xticks(list(x), labels)
    ax.set_ylabel("ms per pair")
    ax.set_title("Model alone, same weights, 2 threads")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_service(cells: list[dict], path: Path) -> None:
    import matplotlib.pyplot as plt

    payloads = list(dict.fromkeys(cell["payload"] for cell in cells))
    fig, axes = plt.subplots(2, len(payloads), figsize=(4.2 * len(payloads), 6.5), squeeze=False)
    for column, payload in enumerate(payloads):
        for mode, style in MODE_STYLES.items():
            rows = sorted(
                (c for c in cells if c["payload"] == payload and c["mode"] == mode), key=lambda c: c["clients"]
            )
            if not rows:
                continue
            clients = [c["clients"] for c in rows]
            axes[0][column].plot(clients, [c["pairs_per_s"] for c in rows], style, label=mode_label(rows[0]))
            axes[1][column].plot(clients, [c["p50_ms"] or math.nan for c in rows], style, label=f"p50, {mode}")
            axes[1][column].plot(
                clients, [c["p99_ms"] or math.nan for c in rows], style, alpha=0.5, label=f"p99, {mode}"
            )
        axes[0][column].set_title(f"payload: {payload}")
        axes[0][column].set_ylabel("pairs/s")
        axes[1][column].set_ylabel("latency ms")
        axes[1][column].set_yscale("log")
        axes[0][column].set_ylim(bottom=0)
        ticks = sorted({c["clients"] for c in cells if c["payload"] == payload})
        for row in (0, 1):
            axes[row][column].set_xscale("log", base=2)
            axes[row][column].set_xticks(ticks, [str(t) for t in ticks])
            axes[row][column].set_xlabel("concurrent clients")
            axes[row][column].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_overload(overload: dict, path: Path) -> None:
    import matplotlib.pyplot as plt

    fig, (top, middle, bottom) = plt.subplots(3, 1, figsize=(8, 7.5), sharex=True)
    by_status: dict[str, dict[int, int]] = {}
    for row in overload["per_second"]:
        by_status.setdefault(row["status"], {})[row["t"]] = row["count"]
    seconds = range(int(overload["seconds"]) + 1)
    for status, counts in sorted(by_status.items()):
        top.plot(list(seconds), [counts.get(t, 0) for t in seconds], label=f"{status}")
    top.set_ylabel("requests sent per s,\nby final answer")
    top.legend(fontsize=8)
    times, mbs = zip(*overload["rss_samples"], strict=True) if overload["rss_samples"] else ((), ())
    middle.plot(times, mbs)
    middle.set_ylabel("service RSS (MB)")
    probe = overload.get("ready_probe_samples", [])
    bottom.plot([s["t"] for s in probe], [s["ms"] for s in probe], ".")
    bottom.set_ylabel("GET /ready (ms)")
    bottom.set_xlabel("seconds since the overload began")
    top.set_title(f"{overload['rate_per_s']:.1f} requests/s offered (Poisson) for {overload['seconds']:.0f} s")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_profile(profile: dict, path: Path) -> None:
    import matplotlib.pyplot as plt

    rows = profile["by_block_type"][::-1]
    fig, ax = plt.subplots(figsize=(7, 3))
    ax.barh([r["name"] for r in rows], [100 * r["share"] for r in rows])
    ax.set_xlabel("% of kernel time per call")
    ax.set_title(f"ONNX Runtime profile, batch {profile['batch']}, N = {profile['points']}")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


# ---------------------------------------------------------------- sections


def model_section(model: dict | None, plots: Path, lines: list[str]) -> None:
    lines += ["## Model: ONNX Runtime vs eager torch", ""]
    if model is None:
        lines += ["Not run: `docs/benchmarks/model.json` is missing (run `bench/bench_model.py`).", ""]
        return
    rows = model["rows"]
    lines += [
        f"`{model['command']}` ({model['when']}): the weights given by `--weights`, exported to ONNX; both "
        "runtimes compute the same evaluation-mode model (BatchNorms folded, as exported) on the same random "
        "unit-cube clouds with "
        f"{model['threads']} threads, called in turn round after round with a short pause before each call; median "
        "of the repeats, per pair (a batch's time divided by its size). The speed-up is the ratio of the two "
        "medians, and per round the median (and range) of each round's ratio of two calls made back to back, which "
        "a change of the machine's speed between rounds reaches less. Peak RSS is of the benchmark process, which "
        "holds torch, the model and ONNX Runtime together. Both columns are timed in that one process; "
        "`bench/profile_model.py` and `bench/machine_check.py` time the same "
        "ONNX Runtime call in processes without torch (sections below).",
        "",
        "| preset | N | batch | ORT ms/pair | eager ms/pair | ORT speed-up | per round (range) | peak RSS MB |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        low, high = r.get("speedup_paired_range") or (None, None)
        per_round = f"{fmt(r.get('speedup_paired'), 2)}x ({fmt(low, 2)}-{fmt(high, 2)}x)" if low else "-"
        lines.append(
            f"| {r['preset']} | {r['points']} | {r['batch']} | {fmt(r['ort_ms_per_pair'], 1)} | "
            f"{fmt(r['eager_ms_per_pair'], 1)} | {fmt(r['speedup'], 2)}x | {per_round} | {fmt(r['peak_rss_mb'])} |"
        )
    plot_model(rows, plots / "model.png")
    lines += ["", "![ORT vs eager](benchmarks/model.png)", ""]


def profile_section(profile: dict | None, plots: Path, lines: list[str]) -> None:
    lines += ["### Where a model call spends its time", ""]
    if profile is None:
        lines += ["Not run: `docs/benchmarks/profile.json` is missing (run `bench/profile_model.py`).", ""]
        return
    lines += [
        f"`{profile['command']}`: ONNX Runtime's profiler on `{profile['model']}`, batch {profile['batch']}, "
        f"N = {profile['points']}, {profile['threads']} threads, {profile['runs']} calls after warm-up. One call takes "
        f"{fmt(profile['ms_per_call_unprofiled_median'], 1)} ms without the profiler "
        f"({fmt(profile['ms_per_call_profiled_mean'], 1)} ms with it; kernels are "
        f"{profile['kernel_share_of_run']:.0%} of that). Nodes are attributed by the module the exporter named them "
        "after; the FRB's block weights are shared, so each module's time is its total over the 3 x 3 unrolled calls.",
        "",
        "| block type | ms per call | share |",
        "|---|---:|---:|",
    ]
    lines += [f"| {r['name']} | {fmt(r['ms_per_call'], 2)} | {r['share']:.1%} |" for r in profile["by_block_type"]]
    lines += ["", "| operator (top 10) | ms per call | share |", "|---|---:|---:|"]
    lines += [f"| {r['name']} | {fmt(r['ms_per_call'], 2)} | {r['share']:.1%} |" for r in profile["by_op_type"][:10]]
    plot_profile(profile, plots / "profile.png")
    lines += ["", "![profile](benchmarks/profile.png)", ""]


PAYLOAD_TEXT = {
    "model": "768 points per cloud (the network's own size), JSON",
    "scan": "real scans, 12k-100k points per cloud, JSON",
    "scan-npz": "the same real scans as one raw NPZ body",
}


def calls_section(calls: dict | None, lines: list[str]) -> None:
    lines += ["## Model calls side by side", ""]
    if calls is None:
        lines += ["Not run: `docs/benchmarks/calls.json` is missing (run `bench/bench_calls.py`).", ""]
        return
    lines += [
        f"`{calls['command']}` ({calls['when']}, model `{calls['model']['version']}`, file "
        f"`{calls['model']['file']}`): pairs/s of the model alone (batch 1, no HTTP), called back to back by one "
        "thread on a 2-thread ONNX Runtime session (what the service gives a call that runs alone) or by two threads "
        "at once on a 1-thread session (what it gives calls side by side under load), in alternating "
        f"{calls['window_s']:g}-second windows.",
        "",
        "| window | one 2-thread call at a time, pairs/s | two 1-thread calls at once, pairs/s | ratio |",
        "|---:|---:|---:|---:|",
    ]
    for index, window in enumerate(calls["windows"], 1):
        one, two = window["one_2_thread_call"], window["two_1_thread_calls"]
        lines.append(f"| {index} | {fmt(one, 2)} | {fmt(two, 2)} | {two / one:.2f}x |")
    lines += [
        "",
        f"Median ratio {calls['median_ratio']:.2f}x. In the service, HTTP, parsing and the load generator share "
        "the same CPUs: its rows are in the next section (modes `off`, the default, and `1call`).",
        "",
    ]


def service_section(service: dict | None, plots: Path, lines: list[str]) -> None:
    lines += ["## Service: throughput and latency", ""]
    if service is None:
        lines += ["Not run: `docs/benchmarks/service.json` is missing (run `bench/bench_service.py`).", ""]
        return
    lines += [
        f"`{service['command']}` ({service['when']}, {service['machine']['cpus']} CPUs): one `python -m service` "
        "process per mode with the shipped model. Mode off is the default settings (`IFNET_MAX_BATCH_SIZE=1`, "
        "`IFNET_MODEL_CALLS=2`: a model call that starts alone runs on both ONNX Runtime threads, two calls side by "
        "side on one each); on is the same with batches of up to 4 pairs; 1call runs one call at a time on both "
        "threads (`IFNET_MODEL_CALLS=1`). "
        f"closed-loop httpx asyncio clients on 127.0.0.1. Each payload first gets {service['warmup_s']:g} s of "
        f"unmeasured load; each row then sends for {service['duration_s']:g} s and waits for the answers still in "
        "flight, which count (and so does the time). Latencies are of successful requests, client-side. The load "
        "generator runs on the same 2 CPUs as the service (its share is in `load gen CPUs`). Batch, queue and "
        "model-call figures are /metrics deltas over the measured seconds; RSS is the service's peak resident memory "
        "(VmHWM) so far.",
        "",
    ]
    for payload in dict.fromkeys(cell["payload"] for cell in service["cells"]):
        rows = [cell for cell in service["cells"] if cell["payload"] == payload]
        points = ", ".join(str(p) for p in rows[0]["points_per_cloud"])
        lines += [
            f"**{payload}**: {PAYLOAD_TEXT.get(payload, payload)} (points per cloud: {points})",
            "",
            "| mode | clients | pairs/s | p50 ms | p95 ms | p99 ms | mean batch | queue ms | model call ms "
            "| service CPUs | load gen CPUs | RSS MB | answers |",
            "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|",
        ]
        for c in sorted(rows, key=lambda c: (list(MODE_STYLES).index(c["mode"]), c["clients"])):
            lines.append(
                f"| {mode_label(c)} | {c['clients']} | {fmt(c['pairs_per_s'], 2)} | "
                f"{fmt(c['p50_ms'])} | {fmt(c['p95_ms'])} | {fmt(c['p99_ms'])} | {fmt(c['mean_batch'], 2)} | "
                f"{fmt(c['mean_queue_ms'])} | {fmt(c['mean_inference_ms'])} | {fmt(c['server_cpus'], 2)} | "
                f"{fmt(c['loadgen_cpus'], 2)} | {fmt(c['server_vmhwm_mb'])} | {statuses(c['statuses'])} |"
            )
        lines.append("")
    plot_service(service["cells"], plots / "service.png")
    lines += ["![service throughput and latency](benchmarks/service.png)", ""]


def scaling_section(scaling: dict | None, lines: list[str]) -> None:
    lines += ["## 16 clients against one, interleaved", ""]
    if scaling is None:
        lines += ["Not run: `docs/benchmarks/scaling.json` is missing (run `bench/bench_scaling.py`).", ""]
        return
    modes = list(scaling["modes"])
    lines += [
        f"`{scaling['command']}` ({scaling['when']}, model `{scaling['model']['version']}`): one service process per "
        "mode, all running throughout; windows of "
        f"{scaling['window_s']:g} s with 1 and with 16 closed-loop clients (768-point JSON pairs) alternate, the "
        "order rotating each round, so that both client counts of a round meet the same phase of the machine. "
        "Each cell: pairs/s at 16 / 1 clients and their ratio.",
        "",
        "| round | " + " | ".join(mode_label({"mode": m, **scaling["modes"][m]}) for m in modes) + " |",
        "|---:|" + "---:|" * len(modes),
    ]
    for index, measured in enumerate(scaling["rounds"], 1):
        cells = []
        for mode in modes:
            many, one = measured[f"{mode}/16"]["pairs_per_s"], measured[f"{mode}/1"]["pairs_per_s"]
            cells.append(f"{many:.2f} / {one:.2f} ({many / one:.2f}x)")
        lines.append(f"| {index} | " + " | ".join(cells) + " |")
    medians = []
    for mode in modes:
        result = scaling["modes"][mode]
        rates = result["median_pairs_per_s"]
        medians.append(
            f"{mode}: ratio {result['median_ratio']:.2f}x, {rates['16']:.2f} pairs/s at 16 clients and "
            f"{rates['1']:.2f} at 1 (p50 {result['median_p50_ms_1_client']:.0f} ms)"
        )
    lines += ["", "Medians over the rounds: " + "; ".join(medians) + ".", ""]


METHOD_ORDER = ["IFNet", "IFNet + ICP", "Open3D ICP (identity init)", "FPFH + RANSAC (Open3D) + ICP"]


def accuracy_section(evaluation: dict | None, source: Path, lines: list[str]) -> None:
    lines += ["## Accuracy vs speed", ""]
    if evaluation is None:
        lines += [
            f"Not available: `{source.relative_to(ROOT) if source.is_relative_to(ROOT) else source}` is missing. "
            "Run `python -m model.training.evaluate`, then `python bench/report.py`.",
            "",
        ]
        return
    results = evaluation["results"]
    sets = list(results)
    methods = sorted(
        {method for rows in results.values() for method in rows},
        key=lambda m: (METHOD_ORDER.index(m) if m in METHOD_ORDER else len(METHOD_ORDER), m),
    )
    pairs = ", ".join(f"{name} {next(iter(rows.values()))['pairs']}" for name, rows in results.items())
    shown = source.relative_to(ROOT) if source.is_relative_to(ROOT) else source
    lines += [
        f"From `{shown}` (model `{evaluation['model']}`): "
        f"every method on the same pairs (per set: {pairs}). Each cell: recall (rotation < 1 deg and translation "
        "< 0.01) / mean isotropic rotation error in degrees; time is the median ms per pair of each set, "
        "single process, as the evaluation ran it.",
        "",
        "| method | " + " | ".join(sets) + " | ms per pair (" + " / ".join(sets) + ") |",
        "|---|" + "---:|" * len(sets) + "---:|",
    ]
    for method in methods:
        cells, times = [], []
        for name in sets:
            row = results[name].get(method)
            if row is None:
                cells.append("-")
                times.append("-")
                continue
            cells.append(f"{row['recall_1deg_001']:.2f} / {row['iso_r_mean']:.3g}")
            times.append(fmt(row["ms_per_pair"], 1))
        lines.append(f"| {method} | " + " | ".join(cells) + " | " + " / ".join(times) + " |")
    lines.append("")


def settings_text(overload: dict) -> str:
    """The service settings an overload record names, e.g. "max batch 1, 2 model calls, queue 64, "."""
    settings = overload["settings"]
    return (
        f"max batch {settings['max_batch_size']}, {settings['model_calls']} model calls, queue "
        f"{settings['max_queue_size']}, {settings['max_in_flight']} requests in flight, "
    )


def overload_section(overload: dict | None, plots: Path, lines: list[str]) -> None:
    lines += ["## Overload and shutdown", ""]
    if overload is None:
        lines += ["Not run: `docs/benchmarks/overload.json` is missing (run `bench/bench_overload.py`).", ""]
        return
    o, s, v = overload["overload"], overload["sigterm"], overload["verdict"]
    capacity = overload.get("capacity_run", {})
    rss = o.get("rss", {})
    probe = o.get("ready_probe_during", {})
    lines += [
        f"`{overload['command']}` ({overload['when']}): one service process with the shipped settings ("
        f"{settings_text(overload)}request timeout {overload['request_timeout_s']:g} s), JSON pairs of "
        f"{', '.join(str(n) for n in overload['payload_points'])} points per cloud.",
        "",
        f"- Capacity: {fmt(overload['capacity_pairs_per_s'], 2)} pairs/s "
        + (
            f"({capacity.get('clients')} closed-loop clients for {fmt(capacity.get('seconds'), 0)} s, p50 "
            f"{fmt(capacity.get('p50_ms'))} ms)."
            if capacity
            else "(given on the command line)."
        ),
        f"- Overload: Poisson arrivals at {fmt(o['rate_per_s'], 2)} requests/s for {fmt(o['seconds'])} s: "
        f"{o['requests']} requests, answers {statuses(o['statuses'])}; {fmt(o['pairs_per_s'], 2)} pairs/s served "
        f"(mean batch {fmt(o['batching']['mean_batch'], 2)}). Batcher rejections: "
        f"{statuses({reason: int(count) for reason, count in o['rejections'].items()})}.",
        f"- Accepted requests: p50 {fmt(o['p50_ms'])} ms, p99 {fmt(o['accepted_p99_ms'])} ms, max "
        f"{fmt(o['max_ms'])} ms (timeout {overload['request_timeout_s'] * 1000:,.0f} ms). 429 answers: p99 "
        f"{fmt(o['rejected_p99_ms'])} ms.",
        f"- Memory: {fmt(overload.get('rss_ready_mb'))} MB when ready; during the overload "
        f"{fmt(rss.get('after_warmup_mb'))} MB after 10 s, {fmt(rss.get('end_mb'))} MB at the end, max "
        f"{fmt(rss.get('max_mb'))} MB, trend {fmt(rss.get('slope_mb_per_min'), 1)} MB/min.",
        f"- `GET /ready` once a second during the overload: {statuses(probe.get('statuses', {}))}, p50 "
        f"{fmt(probe.get('p50_ms'), 1)} ms, max {fmt(probe.get('max_ms'), 1)} ms. Right after the last answer: "
        f"queue {o['health_after']['queue_depth']}, in flight {o['health_after']['in_flight']}, `/ready` 200 after "
        f"{fmt(o['ready_after_s'], 2)} s.",
        f"- SIGTERM after {s['sigterm_after_s']:g} s of {s['clients']} closed-loop clients: "
        f"{s['in_flight_at_sigterm']} requests in flight, answered {statuses(s['in_flight_outcomes'])}; "
        "requests sent after the signal: "
        f"{statuses(s['sent_after_sigterm_outcomes'])} (from the signal on, no new request is "
        "taken: a new connection is refused, an idle kept-alive one is closed; neither reached the app, so a "
        f"client can retry them). Exit code {s['exit_code']} after {fmt(s['exited_after_s'], 2)} s; server log: "
        f"{overload['log_checks']['tracebacks']} tracebacks, batcher drained: "
        f"{overload['log_checks']['batcher_drained']}.",
        "",
        "| check | result |",
        "|---|---|",
    ]
    lines += [f"| {name.replace('_', ' ')} | {'yes' if ok else '**no**'} |" for name, ok in v.items()]
    plot_overload(o, plots / "overload.png")
    lines += ["", "![overload timeline](benchmarks/overload.png)", ""]


def goals_section(model, profile, service, scaling, overload, checks, lines: list[str]) -> None:
    rows = []
    # Every call bench/machine_check.py timed on the served file, pooled over its checks: many calls
    # spread over hours, so less at the mercy of one phase of the machine than any single run.
    served = [c for c in checks or [] if c.get("model", {}).get("file") == shipped_file_hash()]
    calls_ms = [sample[1] for check in served for sample in check["samples"]]
    if calls_ms:
        median = float(np.median(calls_ms))
        within = sum(ms <= GOAL_P50_MS for ms in calls_ms) / len(calls_ms)
        rows.append(
            (
                f"shipped model <= {GOAL_P50_MS:g} ms per pair: model alone, machine_check.py (ORT, 2 threads, "
                f"batch 1, N = 768; every call of the {len(served)} checks on the served file, "
                f"{served[0]['when'][:10]} to {served[-1]['when'][:10]})",
                f"median {median:.1f} ms over {len(calls_ms)} calls; {within:.0%} within {GOAL_P50_MS:g} ms",
                verdict(median, GOAL_P50_MS, True),
            )
        )
    model_rows = (model or {}).get("rows", [])
    base = next(
        (
            r
            for r in model_rows
            if r["batch"] == 1 and r["points"] == 768 and r["preset"] == shipped_metadata().get("preset")
        ),
        None,
    )
    rows.append(
        (
            f"shipped model <= {GOAL_P50_MS:g} ms per pair: model alone, bench_model.py (ORT, batch 1, N = 768, "
            "median; in the process that also runs torch)",
            fmt(base and base["ort_ms_per_pair"], 1, " ms"),
            verdict(base and base["ort_ms_per_pair"], GOAL_P50_MS, True),
        )
    )
    if profile is not None and profile["batch"] == 1:
        value = profile["ms_per_call_unprofiled_median"]
        rows.append(
            (
                f"shipped model <= {GOAL_P50_MS:g} ms per pair: model alone, profile_model.py (ORT, batch 1, "
                f"N = {profile['points']}, median, ONNX Runtime only)",
                fmt(value, 1, " ms"),
                verdict(value, GOAL_P50_MS, True),
            )
        )
    cells = (service or {}).get("cells", [])

    def cell(mode: str, payload: str, clients: int) -> dict | None:
        return next((c for c in cells if (c["mode"], c["payload"], c["clients"]) == (mode, payload, clients)), None)

    for mode in ("off", "on"):
        one = cell(mode, "model", 1)
        if one is None:
            continue
        rows.append(
            (
                f"shipped model <= {GOAL_P50_MS:g} ms per pair: model call inside the service ({mode_label(one)}, "
                "1 client, mean)",
                fmt(one["mean_inference_ms"], 0, " ms"),
                verdict(one["mean_inference_ms"], GOAL_P50_MS, True),
            )
        )
        rows.append(
            (
                f"shipped model <= {GOAL_P50_MS:g} ms per pair: service end to end ({mode_label(one)}, 1 client, "
                "768-point JSON pair, p50)",
                fmt(one["p50_ms"], 0, " ms"),
                verdict(one["p50_ms"], GOAL_P50_MS, True),
            )
        )
    for key, how in (
        ("speedup", "ratio of the two medians"),
        ("speedup_paired", "median of each round's ratio, the two calls back to back"),
    ):
        speedups = [r[key] for r in model_rows if r.get(key) and not math.isnan(r[key])]
        if key == "speedup" or speedups:
            rows.append(
                (
                    f"ORT >= {GOAL_ORT_SPEEDUP:g}x eager ({how}; every batch and N measured, the lowest)",
                    fmt(min(speedups), 2, "x") if speedups else "-",
                    verdict(min(speedups) if speedups else None, GOAL_ORT_SPEEDUP, False),
                )
            )
    for payload in ("model", "scan"):
        for mode in MODE_STYLES:
            sixteen, single = cell(mode, payload, 16), cell(mode, payload, 1)
            label = mode_label(single) if single else mode
            goal = f"throughput at 16 clients >= {GOAL_SCALING:g}x one at a time ({payload} payload, {label})"
            if not (sixteen and single and single["pairs_per_s"]):
                rows.append((goal, "-", verdict(None, GOAL_SCALING, False)))
                continue
            ratio = sixteen["pairs_per_s"] / single["pairs_per_s"]
            model_ms = [c["mean_inference_ms"] / c["mean_batch"] for c in (single, sixteen)]
            result = verdict(ratio, GOAL_SCALING, False)
            # With one single-pair call at a time a pair's model time does not depend on the clients;
            # when it does, the machine's speed changed between the two rows and the ratio measures that.
            if mode == "1call" and model_ms[0] > MACHINE_DRIFT * model_ms[1]:
                result += f" (but the model ran {model_ms[0] / model_ms[1]:.2f}x slower per pair in the 1-client row)"
            rows.append(
                (
                    goal,
                    f"{ratio:.2f}x ({sixteen['pairs_per_s']:.2f} / {single['pairs_per_s']:.2f} pairs/s; model "
                    f"{model_ms[0]:.0f} / {model_ms[1]:.0f} ms per pair at 1 / 16 clients)",
                    result,
                )
            )
    for mode, result in (scaling or {}).get("modes", {}).items():
        label = mode_label({"mode": mode, **result})
        rows.append(
            (
                f"throughput at 16 clients >= {GOAL_SCALING:g}x one at a time (model payload, {label}, interleaved "
                "windows of bench_scaling.py, median ratio)",
                f"{result['median_ratio']:.2f}x ({min(result['ratios']):.2f}-{max(result['ratios']):.2f}x over "
                f"{len(result['ratios'])} rounds)",
                verdict(result["median_ratio"], GOAL_SCALING, False),
            )
        )
    peaks = [c["server_vmhwm_mb"] for c in cells]
    if overload:
        peaks.append(overload["overload"]["rss"].get("max_mb", 0.0))
    peak = max(peaks) if peaks else None
    rows.append(
        (
            f"service RSS <= {GOAL_RSS_MB / 1024:g} GB (the highest of bench_service.py's per-run peaks (VmHWM) and "
            "bench_overload.py's sampled maximum during overload)",
            fmt(peak, 0, " MB"),
            verdict(peak, GOAL_RSS_MB, True),
        )
    )
    lines += ["## Goals", "", "| goal | measured | verdict |", "|---|---:|---|"]
    lines += [f"| {goal} | {value} | {result} |" for goal, value, result in rows]
    lines.append("")


RELIABILITY = [
    (
        "Schemathesis on the OpenAPI schema, every route: no 5xx, responses match the schema",
        "`tests/test_reliability_schema.py`: 25 generated cases per operation plus schemathesis's coverage "
        "scenarios, several hundred requests; status code, content type, headers and body checked",
    ),
    (
        "Rigid motions recovered by the normalise/denormalise round trip",
        "`tests/test_reliability_properties.py`: through `Normalisation` alone (float64 rounding) and through "
        "`register_clouds` (deduplication, resampling, `init`, float32 network input)",
    ),
    (
        "Random junk raises only validation errors",
        "`tests/test_reliability_properties.py` (`as_points`, `as_rigid_transform`, the options model, "
        "`register_clouds`); over HTTP: `tests/test_service_fuzz.py`",
    ),
    ("Overload at 2x capacity for 60 s", "`bench/bench_overload.py`, section above"),
    (
        "Queue full, or too many requests in progress (checked before the body is read): 429 with Retry-After",
        "`tests/test_service_batching.py::test_a_full_queue_answers_429_with_retry_after`, "
        "`tests/test_service_batching.py::test_requests_beyond_the_in_flight_limit_get_429_before_their_body_is_read`",
    ),
    (
        "Missing model file: startup fails clearly",
        "`tests/test_service_process.py::test_startup_fails_clearly_without_a_model`, `tests/test_service_engine.py`",
    ),
    (
        "Corrupt model file: startup fails clearly, never a half-alive server",
        "`tests/test_reliability_faults.py`: garbage, truncated and empty files through `python -m service` and "
        "`uvicorn --factory`: non-zero exit, the reason printed, the port never opened",
    ),
    (
        "A request timing out mid-batch does not affect the others",
        "`tests/test_reliability_faults.py::test_a_pair_timing_out_mid_batch_does_not_affect_the_others`; while "
        "queued: `tests/test_service_batching.py::test_a_request_that_waits_too_long_gets_504_and_leaves_the_batch`",
    ),
    (
        "SIGTERM during load finishes in-flight requests",
        "`tests/test_service_process.py::test_sigterm_finishes_in_flight_requests_then_exits`; under sustained load: "
        "`bench/bench_overload.py`",
    ),
    (
        "A client disconnect leaves no stuck work",
        "`tests/test_reliability_faults.py`: a client leaving while its pair is inside the model, and real uvicorn "
        "with clients resetting mid-upload and mid-processing (answered 499, in-flight and queue back to 0, no 500, "
        "no traceback); while queued: `tests/test_service_batching.py`",
    ),
    (
        "Body size limit enforced before parsing",
        "`tests/test_reliability_security.py`: a declared length over the limit gets 413 without one byte read, a "
        "streamed body is cut at the limit before any parser runs; `tests/test_service_api.py` (413 statuses; a "
        "gzip body is held to the limit as it inflates, a 100 MB bomb refused with under 4 MB held)",
    ),
    (
        "Connections: a request-head deadline (408) and size limit (431); an answer given before the body is "
        "read still reaches a client that asked to close the connection",
        "`tests/test_reliability_security.py`: on a real process, silent and slowloris connections closed, a head "
        "over the limit refused whether it arrives in one read or several, a large body never counted; urllib "
        "sending 8 MB without the API key reads its 401 (a reset without the drain), the drain cut at the body limit",
    ),
    (
        "Optional API key, constant-time compare, 401",
        "`tests/test_reliability_security.py`: every key goes through `secrets.compare_digest`, no `==` on the "
        "secret in `service/`, /register answers 401 before reading the body; "
        "`tests/test_service_api.py::test_api_key`",
    ),
    (
        "No pickle in input parsing",
        "`tests/test_reliability_security.py`: AST check of `service/`; pickled NPY in multipart, raw NPY and NPZ "
        "bodies and raw pickles refused with pickle's loaders patched to fail and a payload that would record its "
        "execution; `tests/test_service_formats.py::test_pickled_npy_is_refused`",
    ),
    ("Container runs as non-root", "`tests/test_container.py`"),
]


def reliability_section(lines: list[str]) -> None:
    lines += [
        "## Reliability evidence",
        "",
        "Fast checks run with the test suite (`python -m pytest`); the long ones are the benchmarks above.",
        "",
        "| issue item | where |",
        "|---|---|",
    ]
    lines += [f"| {item} | {where} |" for item, where in RELIABILITY]
    lines.append("")


def versions_section(model, profile, service, overload, timed: dict[str, dict | None], lines: list[str]) -> None:
    """Which weights each result file measured, so that a mix of models shows."""
    found: dict[str, str] = {}
    if SHIPPED_MODEL.is_file():
        weights = shipped_metadata().get("weights_sha256")
        found["`service/models/ifnet.onnx` now"] = (weights or file_sha256(SHIPPED_MODEL))[:12]
    if model is not None:
        parts = model["command"].split()
        if "--weights" in parts and (ROOT / parts[parts.index("--weights") + 1]).is_file():
            path = ROOT / parts[parts.index("--weights") + 1]
            found["bench_model.py (its --weights file now)"] = file_sha256(path)[:12]
        else:
            found["bench_model.py"] = "random weights"
    if profile is not None:
        found["profile_model.py"] = profile.get("model_version", "not recorded")
    for name, record in (("bench_service.py", service), ("bench_overload.py", overload)):
        if record is not None:
            found[name] = (record.get("model") or {}).get("version", "not recorded")
    distinct = {value for value in found.values() if value not in ("random weights", "not recorded")}
    lines += [
        "Model version (first 12 hex digits of the weights' SHA-256) behind each result: "
        + "; ".join(f"{name}: `{value}`" for name, value in found.items())
        + ("." if len(distinct) <= 1 else ". **The results are not all of the same weights.**"),
        "",
    ]
    # Timings follow the exported file (the same weights export to faster or slower graphs).
    files = {name: timed_file(record) for name, record in timed.items() if record is not None}
    served = shipped_file_hash()
    lines += [
        f"ONNX file (first 12 hex digits of its SHA-256) each timing ran on; served now `{served}`: "
        + "; ".join(f"{name}: `{value}`" for name, value in files.items())
        + (
            "."
            if all(value == served for value in files.values())
            else ". **Some timings are of another file than the served one: rerun those benchmarks.**"
        ),
        "",
    ]


def timed_file(record: dict) -> str:
    model = record.get("model") or {}
    return (model.get("file_sha256") or model.get("file") or "not recorded")[:12]


def machine_section(checks: list[dict] | None, lines: list[str]) -> None:
    lines += ["## The machine during the runs", ""]
    if not checks:
        lines += ["No `docs/benchmarks/machine.json` (run `bench/machine_check.py` around the benchmarks).", ""]
        return
    lines += [
        "This is a shared 2-CPU virtual machine. Timed repeatedly, the same 2-thread model call sometimes takes as "
        "long as the 1-thread call, in phases that last seconds and can cover a whole process: then the second "
        "thread gains nothing. The CPU itself is there: in the same phases two 1-thread calls side by side kept "
        'their full rate (section "Model calls side by side"), so what stalls is the two threads\' cooperation '
        "within a call. `bench/machine_check.py` times the served model "
        "alternately on 2 threads and on 1 thread; run before and after the benchmarks, it shows which phase the "
        "machine was in then (not during each measurement). Any single timing above may be up to the ratio below "
        "slower than the fast phase allows.",
        "",
        "| check | when | model timed | calls | 2 threads ms (median) | 1 thread ms (median) | speed-up (median) | "
        "calls where 2 threads gave < 1.2x |",
        "|---|---|---|---:|---:|---:|---:|---:|",
    ]
    for c in checks:
        lines.append(
            f"| {c['label']} | {c['when']} | {timed_model_label(c)} | {c['pairs']} | "
            f"{fmt(c['two_threads_ms_median'], 1)} | {fmt(c['one_thread_ms_median'], 1)} | "
            f"{fmt(c['speedup_median'], 2)}x | {c['share_second_cpu_missing']:.0%} |"
        )
    lines += [
        "",
        "Rows without a recorded model timed the `fast` preset's 5-neighbour EdgeConv graph, the served graph "
        "until 2026-12-02 10:47 UTC, when the shipped network's 16-neighbour graph (1.09-1.26x as long per call) "
        "replaced it. Rows without a file hash timed an export from before 2026-12-02 13:29 UTC, except the three "
        "of 13:36-13:50 UTC that day: those timed the export made then, which folds BatchNorms and searches only "
        "the other cloud in the attention's kNN (within this machine's noise of the earlier export per call). "
        f"The export shipped now is file `{shipped_file_hash()}`.",
        "",
    ]


@functools.cache
def shipped_file_hash() -> str:
    return file_sha256(SHIPPED_MODEL)[:12] if SHIPPED_MODEL.is_file() else "missing"


@functools.cache
def shipped_metadata() -> dict[str, str]:
    """The served ONNX file's metadata (read once: opening a session costs a second or two)."""
    import onnxruntime as ort

    if not SHIPPED_MODEL.is_file():
        return {}
    options = ort.SessionOptions()
    options.log_severity_level = 3
    session = ort.InferenceSession(str(SHIPPED_MODEL), options, providers=["CPUExecutionProvider"])
    return dict(session.get_modelmeta().custom_metadata_map)


def timed_model_label(check: dict) -> str:
    model = check.get("model")
    if model is None:
        return "not recorded"
    exported = f"; file `{model['file']}`" if "file" in model else ""
    return f"`{model['version']}` ({model['preset']}, EdgeConv k {model['edgeconv_k']}{exported})"


def machine(service: dict | None, overload: dict | None) -> str:
    recorded = (service or {}).get("machine") or (overload or {}).get("machine") or {}
    cpus = recorded.get("cpus")
    return f"{cpus} CPUs" + (f" ({recorded['arch']})" if recorded.get("arch") else "") if cpus else "not recorded"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--results", type=Path, default=ROOT / "docs" / "benchmarks")
    parser.add_argument("--evaluation", type=Path, default=ROOT / "docs" / "evaluation" / "evaluation.json")
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks.md")
    args = parser.parse_args()

    import matplotlib

    matplotlib.use("Agg")
    model = load(args.results / "model.json")
    profile = load(args.results / "profile.json")
    calls = load(args.results / "calls.json")
    service = load(args.results / "service.json")
    scaling = load(args.results / "scaling.json")
    overload = load(args.results / "overload.json")
    evaluation = load(args.evaluation)
    checks = load(args.results / "machine.json")
    plots = args.out.parent / "benchmarks"  # where the page's image links point (the results folder by default)
    plots.mkdir(parents=True, exist_ok=True)

    lines = [
        "# Benchmarks",
        "",
        f"Generated by `python bench/report.py` on {datetime.now(UTC).strftime('%Y-%m-%d %H:%M UTC')} from the result "
        "files in `docs/benchmarks/` and `docs/evaluation/evaluation.json`; rerun the benchmarks named in each "
        f"section to refresh them. Machine: {machine(service, overload)}; all traffic on 127.0.0.1.",
        "",
    ]
    timed = {
        "bench_service.py": service,
        "bench_scaling.py": scaling,
        "bench_calls.py": calls,
        "bench_overload.py": overload,
    }
    versions_section(model, profile, service, overload, timed, lines)
    goals_section(model, profile, service, scaling, overload, checks, lines)
    model_section(model, plots, lines)
    profile_section(profile, plots, lines)
    calls_section(calls, lines)
    service_section(service, plots, lines)
    scaling_section(scaling, lines)
    accuracy_section(evaluation, args.evaluation, lines)
    overload_section(overload, plots, lines)
    machine_section(checks, lines)
    reliability_section(lines)
    args.out.write_text("\n".join(lines).rstrip("\n") + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
