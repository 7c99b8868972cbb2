"""ORB features that adapt to the image (``frontends.orb``), shared by the frontend, the loop
detectors and the verifier."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np
import pytest

from frontends.mono_vo.features import OrbExtractor
from frontends.orb import TRACKING_ORB, OrbConfig, detect_orb, extract_orb, group_order
from frontends.types import CameraIntrinsics, Keyframe

#: The extractor before adaptation: area-scaled budget without a floor, no upsampling, no cells.
FIXED = OrbConfig(min_nfeatures=0, upsample_below=0, min_cell_corners=0)


def texture(width: int, height: int, seed: int = 0) -> np.ndarray:
    """A grey image of random discs and squares (corners everywhere, like a textured scene)."""
    rng = np.random.default_rng(seed)
    image = np.full((height, width), 128, np.uint8)
    for _ in range(width * height // 150):
        x, y = int(rng.integers(0, width)), int(rng.integers(0, height))
        radius, grey = int(rng.integers(2, 8)), int(rng.integers(0, 256))
        if rng.random() < 0.5:
            cv2.circle(image, (x, y), radius, grey, -1)
        else:
            cv2.rectangle(image, (x, y), (x + radius, y + radius), grey, -1)
    return cv2.GaussianBlur(image, (3, 3), 0)


def test_small_image_gets_a_usable_budget() -> None:
    small = texture(160, 120)
    assert len(detect_orb(small, FIXED)) < 100  # ORB's border and coarse levels leave little
    adapted = detect_orb(small)
    assert len(adapted) >= 300
    assert (adapted.keypoints >= 0).all() and (adapted.keypoints[:, 0] < 160).all()
    assert (adapted.keypoints[:, 1] < 120).all()


def test_upsampled_keypoints_are_in_the_original_image() -> None:
    image = texture(200, 150, seed=1)
    shift = np.array([12.0, 8.0])
    moved = cv2.warpAffine(image, np.float32([[1, 0, shift[0]], [0, 1, shift[1]]]), (200, 150))
    config = OrbConfig()
    assert config.upsampled(200, 150)
    a, b = detect_orb(image, config), detect_orb(moved, config)
    distance = np.linalg.norm((a.keypoints[:, None] + shift) - b.keypoints[None], axis=2)
    nearest = distance.min(axis=1)
    # Most corners reappear where the shift puts them, to a pixel (positions are not doubled).
    assert np.mean(nearest < 1.0) > 0.6
    assert a.sizes.max() < 31 * 1.2**7 / 2 + 1


def test_weak_cells_get_corners_at_the_low_threshold() -> None:
    image = texture(640, 480, seed=2)
    right = image[:, 320:].astype(np.float64)
    image[:, 320:] = (128 + 0.12 * (right - 128)).astype(np.uint8)  # low contrast right half
    cells = OrbConfig(nfeatures=6000, scale_by_area=False)
    without = dataclasses.replace(cells, min_cell_corners=0)
    assert int((detect_orb(image, without).keypoints[:, 0] > 330).sum()) == 0
    adapted = detect_orb(image, cells)
    assert len(adapted) == 6000
    assert int((adapted.keypoints[:, 0] > 330).sum()) >= 300


@pytest.mark.parametrize("config", [OrbConfig(), TRACKING_ORB], ids=["place-recognition", "tracking"])
def test_strong_corners_are_never_displaced(config: OrbConfig) -> None:
    """An image whose strong corners fill the budget gets exactly them (KITTI kept its tracking)."""
    image = texture(1241, 376, seed=3)
    image[:100] = 200  # a flat sky: weak cells
    with_cells = detect_orb(image, config)
    without = detect_orb(image, dataclasses.replace(config, min_cell_corners=0))
    np.testing.assert_array_equal(with_cells.keypoints, without.keypoints)
    np.testing.assert_array_equal(with_cells.descriptors, without.descriptors)


def test_frontend_uses_the_shared_extractor() -> None:
    image = texture(320, 240, seed=4)
    camera = CameraIntrinsics(fx=300.0, fy=300.0, cx=160.0, cy=120.0, width=320, height=240)
    features = OrbExtractor(TRACKING_ORB, camera).extract(image)
    shared = detect_orb(image, TRACKING_ORB)
    np.testing.assert_array_equal(features.keypoints, shared.keypoints)
    np.testing.assert_array_equal(features.descriptors, shared.descriptors)
    keypoints, descriptors = extract_orb(image, TRACKING_ORB)
    np.testing.assert_array_equal(keypoints, shared.keypoints)
    np.testing.assert_array_equal(descriptors, shared.descriptors)


def test_budget_floor_and_validation() -> None:
    config = OrbConfig(nfeatures=1000, min_nfeatures=500)
    assert config.features_for(640, 480) == 1000
    assert config.features_for(1241, 376) == round(1000 * 1241 * 376 / (640 * 480))
    assert config.features_for(240, 192) == 500
    assert OrbConfig(nfeatures=300, min_nfeatures=500).features_for(160, 120) == 300
    for bad in ({"cell_px": 4}, {"min_fast_threshold": 30}, {"upsample_below": -1}, {"overdetect": 0.5}):
        with pytest.raises(ValueError, match="ORB config"):
            OrbConfig(**bad)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="8-bit grey"):
        detect_orb(np.zeros((10, 10), np.float32))
    assert len(detect_orb(np.zeros((120, 160), np.uint8))) == 0


@pytest.mark.shared
def test_low_resolution_real_loops_verify(shared: Path) -> None:
    """Real loop pairs (RTAB-Map samples) shrunk to 240x180: the adapted features verify about as
    many as the full-size images do (52 of 76), the fixed extractor a third of that."""
    from slam_backend.verify import VerifierConfig, colmap_camera, verify_two_view

    root = shared / "data" / "loops" / "rtabmap_samples"
    lines = (root / "gt_loop_pairs.txt").read_text().splitlines()
    pairs = [tuple(map(int, line.split())) for line in lines if line.strip() and not line.startswith("#")]
    pairs = pairs[:: max(1, len(pairs) // 60)]
    width, height = 240, 180
    focal = 0.5 * width / np.tan(np.radians(30.0))
    camera = colmap_camera(
        CameraIntrinsics(fx=focal, fy=focal, cx=width / 2, cy=height / 2, width=width, height=height)
    )

    def verified(config: OrbConfig) -> int:
        keyframes: dict[int, Keyframe] = {}
        for index in {i for pair in pairs for i in pair}:
            gray = cv2.imread(str(root / "images" / f"{index:06d}.jpg"), cv2.IMREAD_GRAYSCALE)
            found = detect_orb(cv2.resize(gray, (width, height), interpolation=cv2.INTER_AREA), config)
            keyframes[index] = Keyframe(
                index, index, float(index), np.eye(4), found.keypoints, found.descriptors
            )
        return sum(
            verify_two_view(keyframes[q], keyframes[r], camera, VerifierConfig()).passed for q, r in pairs
        )

    fixed, adapted = verified(FIXED), verified(OrbConfig())
    assert adapted >= 0.6 * len(pairs)
    assert adapted >= 2 * fixed


@pytest.mark.parametrize("integer", [True, False])
def test_group_order_is_lexsorts_order_with_ties_in_input_order(integer: bool) -> None:
    """The tracker's fast path (one integer key) sorts like ``np.lexsort((distance, group))``:
    by group, then distance, equal pairs in input order (which match wins a tie depends on it)."""
    rng = np.random.default_rng(2)
    group = rng.integers(0, 50, 4000)
    distance = rng.integers(0, 20, 4000) if integer else rng.integers(0, 20, 4000) / 4.0
    np.testing.assert_array_equal(group_order(group, distance), np.lexsort((distance, group)))
    assert len(group_order(group[:0], distance[:0])) == 0
