"""Scene pairs from real scans: the split by scene, the paper's indoor and outdoor protocols."""

from types import SimpleNamespace

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="the training tests need torch")

from scipy.spatial import cKDTree  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from model.geometry import (  # noqa: E402
    NETWORK_RADIUS,
    apply_transform,
    random_rotation,
    resample_indices,
    rotation_angle_deg,
    voxel_downsample,
)
from model.training.data import DEFAULT_DATA_DIR  # noqa: E402
from model.training.scenes import (  # noqa: E402
    HELD_OUT_SCENES,
    PROTOCOLS,
    SCAN_FILES,
    ScanPairs,
    load_scans,
    make_scan_pair,
    network_view,
    scene_of,
    teacher_view,
)
from model.training.train import main as train_main  # noqa: E402
from model.training.train import shared_points_coincide, taught_transform  # noqa: E402


def room(rng: np.random.Generator, points: int = 6000) -> np.ndarray:
    """A synthetic scan in metres: a floor and two walls of a 4 x 3 x 2.5 m room, with a box."""
    floor = rng.uniform([0, 0, 0], [4, 3, 0], (points // 4, 3))
    wall_x = rng.uniform([0, 0, 0], [0, 3, 2.5], (points // 4, 3))
    wall_y = rng.uniform([0, 3, 0], [4, 3, 2.5], (points // 4, 3))
    box = rng.uniform([1, 1, 0], [1.6, 1.5, 0.8], (points - 3 * (points // 4), 3))
    return np.concatenate([floor, wall_x, wall_y, box])


@pytest.mark.parametrize("domain", sorted(PROTOCOLS))
def test_scan_pairs_follow_the_domains_protocol_without_shared_points(domain):
    scan = room(np.random.default_rng(0), 20000) * (10.0 if domain == "outdoor" else 1.0)
    pair = make_scan_pair(scan, PROTOCOLS[domain], np.random.default_rng(1))
    expected = 1536 if domain == "indoor" else 2048
    assert pair["source"].shape == (expected, 3) and pair["target"].shape == (expected, 3)
    # No target point is an exact image of a source point: two captures, not one point set.
    moved = apply_transform(pair["source"], pair["rotation"], pair["translation"])
    distances, _ = cKDTree(pair["target"]).query(moved)
    assert distances.min() > 1e-9
    # ... yet the truth brings the source onto the target's surface (within the sampling's spacing).
    spacing = np.median(cKDTree(pair["target"]).query(pair["target"], k=2)[0][:, 1])
    assert np.median(distances) < 2 * spacing


def test_the_teachers_pair_shares_its_points_where_the_crops_overlap():
    rng = np.random.default_rng(3)
    pair = make_scan_pair(room(rng), PROTOCOLS["indoor"], rng)
    source, target = teacher_view(pair, 256, PROTOCOLS["indoor"])
    assert source.shape == target.shape == (256, 3)
    distances, _ = cKDTree(target).query(apply_transform(source, pair["rotation"], pair["translation"]))
    assert 0.3 < np.mean(distances < 1e-9) < 1.0  # partial overlap of one point set


def test_a_polished_teacher_is_exact_and_a_wrong_one_is_dropped():
    """taught_transform on scene pairs: the teacher's estimate refined by GICP on the shared-point
    pair; pairs where the shared points do not then coincide teach nothing."""
    rng = np.random.default_rng(4)
    pairs = ScanPairs([room(np.random.default_rng(i)) for i in range(2)], PROTOCOLS["indoor"], 256, seed=1)
    batch = {key: torch.stack([pairs[i][key] for i in range(2)]) for key in pairs[0]}

    class Teacher(torch.nn.Module):  # 2 deg off on the first pair, upside down on the second
        def forward(self, source, target):
            off = [random_rotation(rng, 2.0)[0], np.diag([1.0, -1.0, -1.0])]
            rotation = torch.stack([torch.from_numpy(o).float() for o in off]) @ batch["rotation"]
            return SimpleNamespace(rotation=rotation, translation=torch.zeros(2, 3))

    rotation, _, taught = taught_transform(Teacher(), batch, "cpu", polish=True)
    assert taught.tolist() == [1.0, 0.0]
    error = rotation_angle_deg(rotation[0].double().numpy(), batch["rotation"][0].double().numpy())
    assert error < 0.05


def test_a_teachers_pose_a_fifth_of_a_degree_off_still_teaches_and_one_three_degrees_off_does_not():
    """GICP polishes a right teacher's pose to within ~0.15 deg, not exactly: that still teaches
    (a student a few degrees off gains from it); a pose degrees off does not."""
    rng = np.random.default_rng(5)
    pair = make_scan_pair(room(rng), PROTOCOLS["indoor"], rng)
    source, target = teacher_view(pair, 768, PROTOCOLS["indoor"])
    moved = apply_transform(source, pair["rotation"], pair["translation"])
    centre = moved.mean(axis=0)

    def off_by(degrees: float) -> np.ndarray:
        axis = np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0)
        return (moved - centre) @ Rotation.from_rotvec(np.radians(degrees) * axis).as_matrix().T + centre

    distances, _ = cKDTree(target).query(moved)
    assert np.mean(distances < 1e-9) > 0.3  # the truth: the shared points coincide exactly
    assert shared_points_coincide(off_by(0.2), target)
    assert not shared_points_coincide(off_by(3.0), target)


@pytest.mark.parametrize("far", [5.0, 1e18], ids=["one-key-per-cell", "too-wide-for-one-key"])
def test_voxel_downsampling_keeps_one_centroid_per_occupied_cell(far):
    points = np.array([[0.0, 0, 0], [0.2, 0, 0], [1.1, 0, 0], [1.2, 0.1, 0], [far, far, 5]])
    cells = voxel_downsample(points, 1.0)
    assert len(cells) == 3
    np.testing.assert_allclose(cells, [[0.1, 0, 0], [1.15, 0.05, 0], [far, far, 5]])  # in the cells' order


def test_network_view_samples_and_normalises_like_the_service():
    rng = np.random.default_rng(2)
    pair = make_scan_pair(room(rng), PROTOCOLS["indoor"], rng)
    source, target, normalisation = network_view(pair["source"], pair["target"], 768)
    assert source.shape == target.shape == (768, 3) and source.dtype == np.float32
    radius = max(np.linalg.norm(source, axis=1).max(), np.linalg.norm(target, axis=1).max())
    assert radius == pytest.approx(NETWORK_RADIUS, rel=1e-5)
    np.testing.assert_allclose(source.mean(axis=0), 0, atol=1e-5)


def test_a_small_scans_crops_are_filled_up_to_the_networks_count_as_the_service_fills_them():
    rng = np.random.default_rng(4)
    pair = make_scan_pair(room(rng)[:1500], PROTOCOLS["indoor"], rng)  # two captures of ~750 points each
    assert len(pair["source"]) < 1536 and len(pair["target"]) < 1536
    source, target, normalisation = network_view(pair["source"], pair["target"], 1536)
    assert source.shape == target.shape == (1536, 3)
    small = pair["source"]
    served = small[resample_indices(len(small), 1536, "fps", np.random.default_rng(0), small)]
    np.testing.assert_allclose(source, normalisation.source(served).astype(np.float32))
    for cloud in teacher_view(pair, 1536, PROTOCOLS["indoor"]):
        assert cloud.shape == (1536, 3)


def test_scan_pairs_are_seeded_by_index_and_epoch():
    scans = [room(np.random.default_rng(i)) for i in range(3)]
    pairs = ScanPairs(scans, PROTOCOLS["indoor"], 64, seed=5)
    first = pairs[1]["source"]
    assert torch.equal(first, pairs[1]["source"])
    pairs.epoch = 1
    assert not torch.equal(first, pairs[1]["source"])


def test_scene_pairs_refuse_object_only_options(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        train_main(["--domain", "indoor", "--noise", "jitter", "--out", str(tmp_path / "run")])
    assert exit_.value.code == 2
    assert "--domain indoor: --noise applies to object pairs only" in capsys.readouterr().err


@pytest.mark.parametrize("domain", sorted(SCAN_FILES))
def test_no_scene_is_both_trained_on_and_held_out(domain):
    if not (DEFAULT_DATA_DIR / SCAN_FILES[domain]).is_file():
        pytest.skip(f"{SCAN_FILES[domain]} not found in {DEFAULT_DATA_DIR} (shared data is not checked out here)")
    train, test = (load_scans(domain, part) for part in ("train", "test"))
    train_scenes, test_scenes = ({scene_of(name) for name in scans} for scans in (train, test))
    assert train_scenes and not train_scenes & test_scenes
    assert test_scenes == set(HELD_OUT_SCENES[domain])  # every held-out scene exists in the data


@pytest.mark.parametrize("domain", sorted(PROTOCOLS))
def test_the_shipped_scene_model_is_the_export_of_its_recorded_weights(domain):
    import json

    onnx = pytest.importorskip("onnx")
    from model.artifacts import DEFAULT_WEIGHTS, SERVED_MODEL, file_sha256

    weights = DEFAULT_WEIGHTS.with_name(f"ifnet-{domain}.pt")
    record = json.loads(weights.with_suffix(".json").read_text())
    assert record["sha256"] == file_sha256(weights)
    assert domain in record["training"]["data"] and "no shared point" in record["training"]["pair_noise"]
    metadata = {p.key: p.value for p in onnx.load(SERVED_MODEL.with_name(f"{domain}.onnx")).metadata_props}
    assert metadata["weights_sha256"] == record["sha256"]
