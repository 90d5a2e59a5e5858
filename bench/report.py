"""docs/benchmarks.md from the result files in docs/benchmarks/ (tables only).

python -m bench.report
"""

import json
import sys
from pathlib import Path

from bench import harness

PAGE = harness.ROOT / "docs" / "benchmarks.md"


def table(header: list[str], rows: list[list]) -> list[str]:
    lines = [
        "| " + " | ".join(header) + " |",
        "|" + "|".join("---" if i == 0 else "---:" for i in range(len(header))) + "|",
    ]
    return lines + ["| " + " | ".join(cell(value) for value in row) + " |" for row in rows] + [""]


def cell(value) -> str:
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.3g}" if abs(value) < 1000 else f"{value:,.0f}"
    if isinstance(value, dict):
        return ", ".join(f"{key}: {cell(item)}" for key, item in value.items())
    return str(value)


def outcome(row: dict | None):
    if row is None:
        return None
    return row["rotation_deg"] if "rotation_deg" in row else f"HTTP {row['status']}"


def provenance(record: dict) -> list[str]:
    model = record.get("model", {})
    return [f"`{record['command']}` ({record['when']}, {record['cpus']} CPUs, model `{model.get('version')}`)", ""]


PAPER_COLUMNS = {"mae_r_deg": "MAE(R) deg", "rmse_r_deg": "RMSE(R) deg", "mae_t": "MAE(t)", "rmse_t": "RMSE(t)"}


def scenes(record: dict) -> list[str]:
    return compare(record, "Scene models: the paper's scene protocols and real pairs", paper=True)


def compare(
    record: dict, title: str = "Registration: network, service and peers on the same pairs", paper: bool = False
) -> list[str]:
    right = record["right"]
    lines = [f"## {title}", "", *provenance(record)]
    lines += [f"right: rotation error <= {right['rotation_deg']} deg and translation error <= "]
    lines[-1] += f"{right['translation_share_of_extent']} x extent; service rows' options: {cell(record['requests'])}"
    if record.get("settings"):
        lines[-1] += f"; rows REQUEST@NAME on a server with the IFNET_* settings {cell(record['settings'])}"
    lines.append("")
    for name, data in record["sets"].items():
        summary = data["summary"]
        peers = list(dict.fromkeys(peer for s in summary.values() for peer in s["ratio_to"]))
        verified = any(s["verified"] is not None for s in summary.values())
        header = ["method", "pairs", "recall", "median rotation error (deg)", "median translation error"]
        header += list(PAPER_COLUMNS.values()) if paper else []
        header += ["verified", "wrong and verified"] if verified else []
        header += [f"time / {peer}" for peer in peers]
        rows = []
        for method, s in summary.items():
            row = [method, s["pairs"], s["recall"], s["median_rotation_deg"], s["median_translation"]]
            row += [s.get(key) for key in PAPER_COLUMNS] if paper else []
            row += [s["verified"], s["wrong_verified"]] if verified else []
            rows.append(row + [f"{s['ratio_to'][peer]:.2f}x" if peer in s["ratio_to"] else None for peer in peers])
        points = sorted({n for pair in data["pairs"] for n in pair["points"]})
        size = f"{points[0]:,}" + (f"-{points[-1]:,}" if points[-1] != points[0] else "")
        lines += [f"### {name}: {len(data['pairs'])} pairs, {size} points per cloud", ""]
        lines += table(header, rows)
        if len(data["pairs"]) <= 8:
            methods = list(summary)
            rows = [
                [pair["pair"], "/".join(f"{n:,}" for n in pair["points"])]
                + [outcome(pair["results"].get(m)) for m in methods]
                for pair in data["pairs"]
            ]
            lines += table(["pair", "points", *(f"{m} rotation error (deg)" for m in methods)], rows)
    return lines


def settings(record: dict) -> list[str]:
    return compare(record, "Service settings: the same requests on servers with other IFNET_* settings")


def scan_views(record: dict) -> list[str]:
    seeds = record["seeds"]
    named = f"{seeds[0]}-{seeds[-1]}" if seeds == list(range(seeds[0], seeds[-1] + 1)) else ", ".join(map(str, seeds))
    return compare(record, f"Real scans: views from {len(seeds)} seeds ({named})")


def symmetric(record: dict) -> list[str]:
    return compare(record, "Any rotation, 100 pairs per set: symmetric shapes")


def scaling(record: dict) -> list[str]:
    lines = ["## Service: 16 clients against 1, alternating windows", "", *provenance(record)]
    rows = [
        [
            name,
            s["settings"] or "-",
            len(s["ratios"]),
            f"{s['median_ratio']:.2f}x",
            f"{min(s['ratios']):.2f}-{max(s['ratios']):.2f}x",
        ]
        for name, s in record["settings"].items()
    ]
    return lines + table(["server", "IFNET_* settings", "rounds", "pairs/s 16 / 1 clients, median", "range"], rows)


def overload(record: dict) -> list[str]:
    lines = ["## Service: overload, then SIGTERM under load", "", *provenance(record)]
    o, term = record["overload"], record["sigterm"]
    rows = [
        ["capacity, 16 clients (pairs/s)", o["capacity_pairs_per_s"]],
        ["offered (requests/s) for seconds", f"{o['offered_per_s']:.2f} for {o['seconds']:.0f}"],
        ["answers", o["statuses"]],
        [
            "accepted p99 (ms): on the wire, from the call (its wait in the generator's pool too); timeout (s)",
            f"{o['accepted_p99_on_wire_ms']:,.0f}, {o['accepted_p99_ms']:,.0f}; {record['request_timeout_s']:g}",
        ],
        [
            "RSS MB of all its processes at 10 s, end, max; slope MB/min",
            "{first:.0f}, {end:.0f}, {max:.0f}; {slope_per_min:+.1f}".format(**o["rss_mb"]),
        ],
        ["/ready during overload", o["ready_during"]],
        [
            "queue depth, in flight after",
            f"{o['health_after'].get('queue_depth')}, {o['health_after'].get('in_flight')}",
        ],
        ["SIGTERM: requests in flight, their answers", f"{term['in_flight']} ({cell(term['in_flight_statuses'])})"],
        ["SIGTERM: exit code, seconds to exit", f"{term['exit_code']}, {term['exited_after_s']:.1f}"],
        [
            "log: tracebacks, batchers drained",
            f"{record['log']['tracebacks']}, {cell(record['log']['batcher_drained'])}",
        ],
    ]
    return lines + table(["measure", "value"], rows)


def soak(record: dict) -> list[str]:
    k = record["soak"]
    settings = ", ".join(f"IFNET_{key.upper()}={value}" for key, value in record.get("settings", {}).items())
    heading = f"## Service: {record['clients']} clients for {k['seconds'] / 60:.0f} minutes, memory"
    lines = [f"{heading}, {settings}" if settings else heading, ""]
    lines += [
        *provenance(record),
        "ModelNet pairs and the real pairs with ground truth, as JSON (half the clients send each kind).",
        "",
    ]
    rows = [
        [index + 1, minute["rss_mb_max"], minute["pairs_per_s"], minute["p99_ms"], minute["statuses"]]
        for index, minute in enumerate(k["minutes"])
    ]
    lines += table(["minute", "RSS MB of all its processes, max", "pairs/s", "p99 ms", "answers"], rows)
    summary = [
        [
            "RSS MB first, end, max; slope over the second half MB/min",
            "{first:.0f}, {end:.0f}, {max:.0f}; {slope_per_min:+.1f}".format(**k["rss_mb"]),
        ],
        ["feature matching processes replaced (IFNET_FEATURE_MATCHING_MAX_MB)", k["feature_matching_replaced"]],
        ["answers; p50 / p99 ms", f"{cell(k['statuses'])}; {k['p50_ms']:,.0f} / {k['p99_ms']:,.0f}"],
        ["/ready during", k["ready_during"]],
    ]
    return lines + table(["measure", "value"], summary)


RENDER = {
    "compare": compare,
    "symmetric": symmetric,
    "scan-views": scan_views,
    "scenes": scenes,
    "settings": settings,
    "scaling": scaling,
    "overload": overload,
    "soak": soak,
    "soak-one-cpu": soak,  # as one pod of deploy/: one worker on one thread
}


def main() -> int:
    lines = ["# Benchmarks", "", "Rendered by `python -m bench.report` from `docs/benchmarks/*.json`.", ""]
    for name, render in RENDER.items():
        path = harness.RESULTS / f"{name}.json"
        if path.is_file():
            lines += render(json.loads(path.read_text()))
    PAGE.write_text("\n".join(lines).rstrip() + "\n")
    print(f"wrote {Path(PAGE).relative_to(harness.ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
