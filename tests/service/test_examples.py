"""The README's command-line example: the shipped sample pair registers to its known transform."""

from pathlib import Path

import numpy as np
from conftest import service_process

from model.geometry import from_matrix, rotation_angle_deg
from service.client import RegistrationClient

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def test_the_sample_pair_registers_to_its_true_transform(tmp_path, shipped_model):
    truth = np.loadtxt(EXAMPLES / "true_transform.txt")
    with service_process(tmp_path, shipped_model) as (_, url, _), RegistrationClient(url) as client:
        plain = client.register_files(EXAMPLES / "source.ply", EXAMPLES / "target.pcd")
        refined = client.register_files(EXAMPLES / "source.ply", EXAMPLES / "target.pcd", refine=True)
    for answer, tolerance_deg in ((plain, 2.0), (refined, 0.5)):
        rotation, translation = from_matrix(np.asarray(answer["transform"]))
        assert rotation_angle_deg(rotation, truth[:3, :3]) < tolerance_deg
        assert np.linalg.norm(translation - truth[:3, 3]) < 0.03  # metres; the table is 1.2 m long
