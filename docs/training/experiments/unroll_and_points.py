"""Does a cheaper network call cost accuracy once GICP refines its answer?

The shipped object weights run with fewer unrolled blocks (time steps x iterations; the block's
weights are shared, so any count runs) and on fewer points per cloud (each cloud
farthest-point sampled), on 40 ModelNet10 test pairs spread over the classes, clean and jittered
(the paper's protocol), in torch on one thread. Prints, per variant and set, the rotation error
(degrees) of the network alone and after `model.geometry.refine` (GICP at 2 point spacings, the
service's refinement), recall at 1 and 2 degrees after it, and the median time of the call:

    python docs/training/experiments/unroll_and_points.py
"""

import dataclasses
import time
from pathlib import Path

import numpy as np
import torch

from model.checkpoint import load_checkpoint
from model.geometry import at_most, refine, rotation_angle_deg
from model.training.data import Protocol, load_split, make_pair

VARIANTS = [(3, 3, 768), (2, 3, 768), (3, 2, 768), (1, 3, 768), (2, 2, 768), (3, 3, 512), (2, 3, 512), (3, 3, 384)]


def main() -> None:
    torch.set_num_threads(1)
    shipped = load_checkpoint(Path("model/weights/ifnet-fast.pt")).model.eval()
    shapes = load_split("same")
    indices = np.linspace(0, len(shapes) - 1, 40).round().astype(int)
    sets = {
        noise: [make_pair(shapes[i], Protocol(noise=noise), np.random.default_rng((7, int(i)))) for i in indices]
        for noise in ("clean", "jitter")
    }
    for time_steps, iterations, points in VARIANTS:
        model = type(shipped)(dataclasses.replace(shipped.config, time_steps=time_steps, n_iters=iterations))
        model.load_state_dict(shipped.state_dict())
        model.eval()
        for noise, pairs in sets.items():
            alone, refined, seconds = [], [], []
            for pair in pairs:
                source, target = at_most(pair["source"], points), at_most(pair["target"], points)
                started = time.perf_counter()
                with torch.no_grad():
                    out = model(torch.from_numpy(source)[None], torch.from_numpy(target)[None])
                seconds.append(time.perf_counter() - started)
                rotation, translation = out.rotation[0].double().numpy(), out.translation[0].double().numpy()
                truth = pair["rotation"].astype(np.float64)
                alone.append(float(rotation_angle_deg(rotation, truth)))
                rotation, _, _ = refine(
                    pair["source"].astype(np.float64), pair["target"].astype(np.float64), rotation, translation
                )
                refined.append(float(rotation_angle_deg(rotation, truth)))
            alone, refined = np.array(alone), np.array(refined)
            print(
                f"{time_steps} x {iterations} blocks, {points} points, {noise:6s}: alone mean {alone.mean():.3f} "
                f"median {np.median(alone):.3f} | refined mean {refined.mean():.3f} median {np.median(refined):.4f} "
                f"recall 1 deg {np.mean(refined < 1):.2f} 2 deg {np.mean(refined < 2):.2f} | "
                f"{1000 * np.median(seconds):.0f} ms",
                flush=True,
            )


if __name__ == "__main__":
    main()
