"""Writes the sample pair: a small asymmetric table scanned twice, as source.ply and target.pcd.

Each file samples the table's surfaces on its own (the two clouds share no point), with a little
noise, and the target is moved by the transform in true_transform.txt. Run from the repository
root: python examples/make_examples.py
"""

from pathlib import Path

import numpy as np

from model.geometry import apply_transform, euler_to_matrix, to_matrix
from service.formats import write_ply

HERE = Path(__file__).resolve().parent
BOXES = [  # (centre, half-size) in metres: a top and four legs of different heights
    ((0.0, 0.0, 0.75), (0.6, 0.4, 0.02)),
    ((0.5, 0.3, 0.37), (0.03, 0.03, 0.37)),
    ((-0.5, 0.3, 0.37), (0.03, 0.03, 0.37)),
    ((0.5, -0.3, 0.37), (0.03, 0.03, 0.37)),
    ((-0.45, -0.25, 0.30), (0.08, 0.08, 0.30)),
]
TRUE_TRANSFORM = to_matrix(euler_to_matrix([10.0, -5.0, 35.0]), np.array([0.3, -0.2, 0.05]))


def scan(count: int, rng: np.random.Generator, noise: float = 0.002) -> np.ndarray:
    """`count` points on the boxes' surfaces, each box sampled in proportion to its area."""
    faces = []  # (centre, half-size, axis, side) of each box face
    for centre, half in BOXES:
        for axis in range(3):
            for side in (-1.0, 1.0):
                faces.append((np.array(centre), np.array(half), axis, side))
    areas = np.array([4 * np.prod(np.delete(half, axis)) for _, half, axis, _ in faces])
    chosen = rng.choice(len(faces), size=count, p=areas / areas.sum())
    points = np.empty((count, 3))
    for row, face in enumerate(chosen):
        centre, half, axis, side = faces[face]
        offset = rng.uniform(-1.0, 1.0, 3) * half
        offset[axis] = side * half[axis]
        points[row] = centre + offset
    return points + rng.normal(scale=noise, size=points.shape)


def write_pcd(path: Path, points: np.ndarray) -> None:
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\n"
        f"COUNT 1 1 1\nWIDTH {len(points)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(points)}\nDATA ascii\n"
    )
    path.write_text(header + "".join(f"{x:.5f} {y:.5f} {z:.5f}\n" for x, y, z in points))


def main() -> None:
    rng = np.random.default_rng(7)
    source = scan(2000, rng)
    target = apply_transform(scan(2000, rng), TRUE_TRANSFORM[:3, :3], TRUE_TRANSFORM[:3, 3])
    write_ply(HERE / "source.ply", source.astype(np.float32))
    write_pcd(HERE / "target.pcd", target)
    np.savetxt(HERE / "true_transform.txt", TRUE_TRANSFORM, fmt="%.6f")


if __name__ == "__main__":
    main()
