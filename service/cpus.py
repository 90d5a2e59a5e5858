"""How many CPUs this process may use: its affinity mask, capped by any cgroup CPU quota."""

import math
import os
from pathlib import Path


def cgroup_cpu_limit(
    root: Path = Path("/sys/fs/cgroup"), proc_cgroup: Path = Path("/proc/self/cgroup")
) -> float | None:
    """CPUs granted by a cgroup CPU quota (v2 `cpu.max` or v1 `cpu.cfs_quota_us`), or None without one.

    The tightest quota along this process's cgroup path counts; inside a container the path is
    usually "/", so the container's own limit is read at the mount root.
    """
    try:
        lines = proc_cgroup.read_text().splitlines()
    except OSError:
        return None
    limits: list[float] = []
    for line in lines:
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        hierarchy, controllers, relative = parts
        if hierarchy == "0" and controllers == "":
            base, reader = root, _read_cpu_max
        elif "cpu" in controllers.split(","):
            base = next((root / name for name in (controllers, "cpu", "cpu,cpuacct") if (root / name).is_dir()), None)
            if base is None:
                continue
            reader = _read_cfs_quota
        else:
            continue
        directory = base / relative.lstrip("/")
        while True:
            if (limit := reader(directory)) is not None:
                limits.append(limit)
            if directory == base or base not in directory.parents:
                break
            directory = directory.parent
    return min(limits) if limits else None


def _read_cpu_max(directory: Path) -> float | None:
    try:
        quota, period = (directory / "cpu.max").read_text().split()[:2]
    except (OSError, ValueError):
        return None
    return None if quota == "max" else int(quota) / int(period)


def _read_cfs_quota(directory: Path) -> float | None:
    try:
        quota = int((directory / "cpu.cfs_quota_us").read_text())
        period = int((directory / "cpu.cfs_period_us").read_text())
    except (OSError, ValueError):
        return None
    return None if quota <= 0 or period <= 0 else quota / period


def available_cpus() -> int:
    """CPUs this process may actually use: its affinity mask, capped by any cgroup quota.

    os.cpu_count() would report the host's cores, far more than a container is allowed.
    """
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cpus = os.cpu_count() or 1
    if (quota := cgroup_cpu_limit()) is not None:
        cpus = min(cpus, math.floor(quota))
    return max(1, cpus)
