"""FISHEYE624 projection and unprojection, HOT3D's crop camera and its remap, the (w, x, y, z) quaternion order."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from hoidata.geometry.crop_camera import (
    MAP_TOLERANCE,
    crop_intrinsics,
    crop_maps,
    crop_rays_in_camera,
    crop_to_fisheye,
    fisheye_grid,
    pinhole_to_crop_frame,
    remap_crop,
)
from hoidata.geometry.fisheye624 import Fisheye624, _distort_with_jacobian, distort
from hoidata.geometry.se3 import matrix_to_quaternion_wxyz, quaternion_wxyz_to_matrix, se3_from_wxyz, se3_to_wxyz

# Aria-RGB-like (15 values: one focal length) and Quest-3-like (16 values) calibrations with every term non-zero
ARIA = [610.0, 703.5, 705.2, 0.40, -0.32, -0.30, 1.60, -1.80, 0.70, -8e-4, -4e-4, 6e-4, -2.5e-4, 4e-4, 1.6e-5]
QUEST = [190.0, 191.5, 319.2, 238.7, 0.30, -0.20, 0.05, 0.01, -0.005, 0.001, 1e-3, -5e-4, 5e-4, -2e-4, 3e-4, 1e-4]


def random_rays(n: int, max_angle: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    theta = np.arccos(rng.uniform(np.cos(max_angle), 1.0, n))  # uniform over the cap
    phi = rng.uniform(-np.pi, np.pi, n)
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1)


@pytest.mark.parametrize("params,size,max_angle", [(ARIA, (1408, 1408), 1.25), (QUEST, (640, 480), 1.3)])
def test_projection_unprojection_round_trip_within_1e3_px(params, size, max_angle):
    cam = Fisheye624.from_params(params, *size)
    rays = random_rays(10_000, max_angle, seed=len(params))
    pix = cam.project(rays * np.random.default_rng(1).uniform(0.2, 3.0, (len(rays), 1)))  # any distance
    back = cam.unproject(pix)
    np.testing.assert_allclose(np.linalg.norm(back, axis=-1), 1.0, atol=1e-12)
    assert np.max(np.linalg.norm(cam.project(back) - pix, axis=-1)) <= 1e-3
    assert np.max(np.arccos(np.clip(np.sum(back * rays, -1), -1, 1))) < 1e-6  # the same ray, not another one


def test_params_of_aria_and_quest():
    aria, quest = Fisheye624.from_params(ARIA, 1408, 1408), Fisheye624.from_params(QUEST, 640, 480)
    assert (aria.fx, aria.fy, aria.cx, aria.cy) == (610.0, 610.0, 703.5, 705.2) and aria.coeffs[0] == 0.40
    assert (quest.fx, quest.fy, quest.cx, quest.cy) == (190.0, 191.5, 319.2, 238.7) and quest.coeffs[-1] == 1e-4
    assert aria.params() == ARIA and quest.params() == QUEST
    with pytest.raises(ValueError, match="15 or 16"):
        Fisheye624.from_params(ARIA[:-1], 10, 10)


def test_without_distortion_the_pixel_radius_is_f_theta():
    cam = Fisheye624(100, 100, 50.0, 50.0, 49.5, 49.5, (0.0,) * 12)
    theta = np.array([0.0, 0.3, 1.0, 1.5, 2.0])  # beyond 90 degrees too
    pts = np.stack([np.sin(theta), np.zeros_like(theta), np.cos(theta)], -1)
    np.testing.assert_allclose(cam.project(pts)[:, 0] - 49.5, 50.0 * theta, atol=1e-12)


def test_each_coefficient_moves_the_pixel_as_its_formula_says():
    p = np.array([0.3, -0.2])
    x, y = p
    s = x * x + y * y
    base = [0.0] * 12
    for index, expected in ((0, p * (1 + 0.1 * s)), (5, p * (1 + 0.1 * s ** 6)),
                            (6, [x + 0.1 * (s + 2 * x * x), y + 0.1 * 2 * x * y]),
                            (7, [x + 0.1 * 2 * x * y, y + 0.1 * (s + 2 * y * y)]),
                            (8, [x + 0.1 * s, y]), (9, [x + 0.1 * s * s, y]), (10, [x, y + 0.1 * s]),
                            (11, [x, y + 0.1 * s * s])):
        coeffs = list(base)
        coeffs[index] = 0.1
        np.testing.assert_allclose(distort(p, coeffs), expected, atol=1e-15, err_msg=f"coefficient {index}")


def test_jacobian_matches_finite_differences():
    cam = Fisheye624.from_params(ARIA, 1408, 1408)
    p = np.random.default_rng(2).uniform(-0.8, 0.8, (50, 2))
    _, jac = _distort_with_jacobian(p, cam.coeffs)
    h = 1e-6
    for axis in range(2):
        step = np.zeros(2)
        step[axis] = h
        fd = (distort(p + step, cam.coeffs) - distort(p - step, cam.coeffs)) / (2 * h)
        np.testing.assert_allclose(jac[..., axis], fd, atol=1e-7)


def test_crop_intrinsics_follow_the_readers_formula():
    K = crop_intrinsics(128, np.deg2rad(60.0))
    assert K[0, 0] == K[1, 1] == pytest.approx(128 / 2 / np.tan(np.deg2rad(30.0)))
    assert K[0, 2] == K[1, 2] == 63.5
    with pytest.raises(ValueError, match="radians"):
        crop_intrinsics(128, 60.0)  # degrees by mistake


def _blob_image(cam: Fisheye624, centre: np.ndarray, sigma: float = 3.0) -> np.ndarray:
    v, u = np.mgrid[0:cam.height, 0:cam.width].astype(np.float64)
    return np.exp(-((u - centre[0]) ** 2 + (v - centre[1]) ** 2) / (2 * sigma * sigma))


def test_a_world_point_lands_where_the_crop_camera_projects_it():
    cam = Fisheye624.from_params(QUEST, 640, 480)
    world_from_camera = se3_from_wxyz(matrix_to_quaternion_wxyz(Rotation.from_euler("xyz", [0.3, -0.5, 0.2]).as_matrix()),
                                      [0.1, -0.2, 1.3])
    point_eye = np.array([0.25, 0.1, 0.35])  # about 38 degrees off the axis: heavily distorted
    point = world_from_camera[:3, :3] @ point_eye + world_from_camera[:3, 3]
    # a crop camera at the fisheye's centre, looking near (not at) the point, rolled
    look = Rotation.align_vectors([point_eye + [0.03, -0.02, 0.0]], [[0, 0, 1]])[0]
    world_from_crop = world_from_camera @ se3_from_wxyz(matrix_to_quaternion_wxyz((look * Rotation.from_euler(
        "z", 0.4)).as_matrix()), [0, 0, 0])
    K, size = crop_intrinsics(96, 0.5), 96
    crop = remap_crop(_blob_image(cam, cam.project(point_eye)).astype(np.float32),
                      crop_maps(cam, world_from_camera, K, world_from_crop, size))
    in_crop = pinhole_to_crop_frame(point, world_from_crop)
    expected = (in_crop @ K.T)[:2] / in_crop[2]
    v, u = np.mgrid[0:size, 0:size]
    w = np.where(crop > 0.2 * crop.max(), crop, 0.0)
    centroid = np.array([(w * u).sum(), (w * v).sum()]) / w.sum()
    assert 10 < expected[0] < size - 10 and 10 < expected[1] < size - 10
    assert np.linalg.norm(centroid - expected) < 0.2


def test_rays_behind_the_fisheye_camera_read_black():
    cam = Fisheye624(64, 64, 12.0, 12.0, 31.5, 31.5, (0.0,) * 12)  # sees 150 degrees off axis
    backwards = se3_from_wxyz([0.0, 0.0, 1.0, 0.0], [0, 0, 0])  # 180 degrees about y: looks along -z
    maps = crop_maps(cam, np.eye(4), crop_intrinsics(32, 1.0), backwards, 32)
    crop = remap_crop(np.full((64, 64), 200, np.uint8), maps)
    assert crop.max() == 0
    assert remap_crop(np.full((64, 64), 200, np.uint8), crop_maps(cam, np.eye(4), crop_intrinsics(32, 1.0),
                                                                 np.eye(4), 32)).min() == 200


def test_quaternion_is_w_first():
    """90 degrees about x takes +y to +z; read as (x, y, z, w) the same numbers are 180 degrees about (1, 1, 0),
    which takes +y to +x: this test fails if the order is swapped anywhere in the chain."""
    q = [np.cos(np.pi / 4), np.sin(np.pi / 4), 0.0, 0.0]
    np.testing.assert_allclose(quaternion_wxyz_to_matrix(q) @ [0, 1, 0], [0, 0, 1], atol=1e-15)
    pose = se3_from_wxyz(q, [1.0, 2.0, 3.0])
    np.testing.assert_allclose(pose @ [0, 1, 0, 1], [1, 2, 4, 1], atol=1e-15)
    np.testing.assert_allclose(Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix(), pose[:3, :3], atol=1e-15)
    rot = Rotation.from_euler("xyz", [0.3, -1.1, 2.0]).as_matrix()
    back = se3_to_wxyz(se3_from_wxyz(matrix_to_quaternion_wxyz(rot), [0, 0, 0]))
    np.testing.assert_allclose(quaternion_wxyz_to_matrix(back["quaternion_wxyz"]), rot, atol=1e-14)
    assert back["quaternion_wxyz"][0] >= 0


def test_max_angle_is_where_the_radial_map_stops_increasing():
    folding = Fisheye624(10, 10, 5.0, 5.0, 4.5, 4.5, (-0.5,) + (0.0,) * 11)  # theta (1 - theta^2 / 2): peak sqrt(2/3)
    assert folding.max_angle() == pytest.approx(np.sqrt(2 / 3), abs=1e-3)
    assert Fisheye624(10, 10, 5.0, 5.0, 4.5, 4.5, (0.0,) * 12).max_angle() == pytest.approx(np.pi)
    rays = random_rays(1000, 0.8, seed=3)  # inside the fold: the unprojection finds the ray, not its mirror branch
    np.testing.assert_allclose(folding.unproject(folding.project(rays)), rays, atol=1e-9)


@pytest.mark.parametrize("params,size", [(ARIA, (1408, 1408)), (QUEST, (640, 480))])
def test_interpolated_crop_maps_within_tolerance_of_the_exact_rays(params, size):
    """crop_maps computes the rays exactly at every GRID_STEP-th pixel and interpolates between them: every pixel of
    60 random crop cameras (field of view 0.2-1.0 rad, centre up to 1 rad off the axis, rolled; 128 and 256 px) is
    within MAP_TOLERANCE of its exact ray, and every crop whose rays stay within 1.1 rad of the axis is interpolated
    (not the exact fallback, which is right but slower: beyond, near the edge of an Aria image, this calibration's
    theta^12 term grows fast and a 128 px crop at 1.16 rad needs a finer grid than step 4)."""
    cam = Fisheye624.from_params(params, *size)
    rng = np.random.default_rng(7)
    interpolated = 0
    for i in range(60):
        crop = 128 if i % 2 else 256
        turn = (Rotation.from_euler("z", rng.uniform(-np.pi, np.pi)) * Rotation.from_euler("x", rng.uniform(0, 1.0))
                * Rotation.from_euler("z", rng.uniform(-np.pi, np.pi)))
        world_from_crop = se3_from_wxyz(matrix_to_quaternion_wxyz(turn.as_matrix()), [0.01, -0.02, 0.0])
        world_from_camera = se3_from_wxyz([1.0, 0.0, 0.0, 0.0], [0.01, -0.02, 0.0])
        K = crop_intrinsics(crop, rng.uniform(0.2, 1.0))
        v, u = np.mgrid[0:crop, 0:crop].astype(np.float64)
        exact = crop_to_fisheye(cam, world_from_camera, K, world_from_crop, np.stack([u, v], -1))
        grid = fisheye_grid(cam, world_from_camera, K, world_from_crop, (crop, crop))
        assert np.abs(grid - exact).max() <= MAP_TOLERANCE
        corners = crop_rays_in_camera(world_from_camera, K, world_from_crop, np.array([[0, 0], [0, crop - 1],
                                                                                     [crop - 1, 0], [crop - 1] * 2]))
        if np.arccos(corners[:, 2].min()) <= 1.1:
            assert np.any(grid != exact)
            interpolated += 1
        maps = crop_maps(cam, world_from_camera, K, world_from_crop, crop)
        assert np.abs(np.stack(maps, -1) - grid).max() < 1e-3  # float32 of the same map
    assert interpolated >= 30


def test_interpolated_map_through_an_affine_grid_and_its_exact_fallback():
    """fisheye_grid on a grid mapped affinely into the crop (a half-size mask grid, mirrored) equals the exact rays
    at those crop pixels within the tolerance; with tolerance 0 the check fails and every pixel is exact."""
    cam = Fisheye624.from_params(ARIA, 1408, 1408)
    world_from_crop = se3_from_wxyz(matrix_to_quaternion_wxyz(Rotation.from_euler("xy", [0.4, -0.3]).as_matrix()),
                                    [0, 0, 0])
    K = crop_intrinsics(256, 0.6)
    grid_to_crop = np.array([[-2.0, 0.0, 255.5], [0.0, 2.0, 0.5], [0.0, 0.0, 1.0]])  # mirrored, twice the pixels
    v, u = np.mgrid[0:128, 0:128].astype(np.float64)
    uv = np.stack([u, v], -1) @ grid_to_crop[:2, :2].T + grid_to_crop[:2, 2]
    exact = crop_to_fisheye(cam, np.eye(4), K, world_from_crop, uv)
    grid = fisheye_grid(cam, np.eye(4), K, world_from_crop, (128, 128), grid_to_crop)
    assert 0 < np.abs(grid - exact).max() <= MAP_TOLERANCE
    assert np.array_equal(fisheye_grid(cam, np.eye(4), K, world_from_crop, (128, 128), grid_to_crop, tolerance=0.0),
                          exact)
