"""Range-image projection, encoding and back-projection."""


import numpy as np
import pytest

from omnilidar.data.range_image import (
    RangeImageSpec,
    beam_angle_features,
    decode,
    encode,
    encoded_min_range,
    from_range_image,
    pixel_angles,
    project,
    to_range_image,
    unproject,
)
from omnilidar.errors import InputError
from omnilidar.lidar.scan import Scan
from omnilidar.lidar.sensors import PRESETS

from real_samples import real_file
SPEC = RangeImageSpec.from_sensor(PRESETS["kitti_hdl64e"])


def test_spec_from_sensor_and_validation():
    assert SPEC.shape == (64, 1024)
    assert (SPEC.fov_up_deg, SPEC.fov_down_deg, SPEC.min_range, SPEC.max_range) == (3.0, -25.0, 1.45, 80.0)
    assert RangeImageSpec.from_sensor(PRESETS["nuscenes_hdl32e"], height=64, width=512).shape == (64, 512)
    with pytest.raises(InputError):
        RangeImageSpec(64, 1024, -25.0, 3.0, 1.45, 80.0)
    with pytest.raises(InputError):
        RangeImageSpec(0, 1024, 3.0, -25.0, 1.45, 80.0)
    with pytest.raises(InputError):
        RangeImageSpec(64, 1024, 3.0, -25.0, 80.0, 1.45)


def test_convention_forward_top_and_seam():
    spec = RangeImageSpec(8, 16, 10.0, -10.0, 0.5, 100.0)
    # forward (az = 0) at u = W/2, elevation just below the top edge -> row 0
    top_fwd = np.array([[10.0, 0.0, 10.0 * np.tan(np.deg2rad(9.0)), 0.5]], np.float32)
    proj = project(top_fwd, spec)
    assert (proj.point_row[0], proj.point_col[0]) == (0, 8)
    # left (az = +pi/2) is left of centre: u = W/4
    left = np.array([[0.0, 10.0, 0.0, 0.5]], np.float32)
    assert project(left, spec).point_col[0] == 4
    # intensity normalised by the scale
    assert project(top_fwd, spec, intensity_scale=2.0).intensity_img[0, 8] == pytest.approx(0.25)


def test_nearest_wins_and_ties_go_to_lower_index():
    spec = RangeImageSpec(4, 8, 10.0, -10.0, 0.5, 100.0)
    pts = np.array([[5, 0, 0, 0.1], [3, 0, 0, 0.2], [3, 0, 0, 0.3], [9, 0, 0, 0.4]], np.float32)
    proj = project(pts, spec)
    r, c = proj.point_row[0], proj.point_col[0]
    assert np.all(proj.point_row == r) and np.all(proj.point_col == c)
    assert proj.point_index_img[r, c] == 1
    assert proj.range_img[r, c] == pytest.approx(3.0)
    assert proj.intensity_img[r, c] == pytest.approx(0.2)
    assert proj.winner.tolist() == [False, True, False, False]
    assert proj.mask.sum() == 1 and (proj.range_img[~proj.mask] == 0).all()


def _check_round_trip(pts: np.ndarray):
    """Project, encode and decode a sweep: the pixels keep their nearest point's range."""
    proj = project(pts, SPEC)
    won = proj.point_index_img[proj.mask]
    np.testing.assert_allclose(proj.range_img[proj.mask], np.linalg.norm(pts[won, :3].astype(np.float64), axis=1), rtol=1e-6)
    img = encode(proj.range_img, proj.intensity_img, SPEC)
    assert img.dtype == np.float32 and img.shape == (2, 64, 1024)
    assert img.min() >= -1.0 and img.max() <= 1.0
    assert np.all(img[:, ~proj.mask] == -1.0)
    d, i, m = decode(img, SPEC)
    assert np.array_equal(m, proj.mask)
    np.testing.assert_allclose(d[m], proj.range_img[m], rtol=1e-5)
    np.testing.assert_allclose(i[m], proj.intensity_img[m], atol=1e-6)
    return proj


def test_full_sweep_round_trip(synthetic_sweep):
    _check_round_trip(synthetic_sweep.points)


def test_real_scan_round_trip_fills_the_image():
    # The spec fits the real sensor: nearly every return lands in the image, which it mostly fills.
    proj = _check_round_trip(np.fromfile(real_file("kitti_object/velodyne/000001.bin"), np.float32).reshape(-1, 4))
    assert proj.valid.mean() > 0.99
    assert 0.6 < proj.mask.mean() < 0.9


def test_encoding_formula_and_min_range_threshold():
    spec = SPEC
    d = np.zeros(spec.shape, np.float32)
    d[0, 0], d[0, 1], d[0, 2], d[0, 3] = 10.0, 1.45, 80.0, 1.46
    img = encode(d, np.full(spec.shape, 0.5, np.float32), spec)
    assert img[0, 0, 0] == pytest.approx(2 * np.log2(11) / np.log2(81) - 1, abs=1e-6)
    assert img[1, 0, 0] == pytest.approx(0.0)
    assert (img[:, 0, 1] == -1).all() and (img[:, 0, 2] == -1).all()  # limits are exclusive
    assert img[0, 0, 3] > encoded_min_range(spec)
    assert encoded_min_range(spec) == pytest.approx(-0.592, abs=1e-3)
    # anything at or below the min-range code decodes to "no return"
    img2 = np.full((2, *spec.shape), -1.0, np.float32)
    img2[0, 0, 0] = encoded_min_range(spec) - 1e-3
    img2[0, 0, 1] = encoded_min_range(spec) + 1e-3
    _, _, m = decode(img2, spec)
    assert not m[0, 0] and m[0, 1] and m.sum() == 1


def test_unproject_row_major_and_pixel_centres():
    spec = RangeImageSpec(4, 8, 10.0, -10.0, 0.5, 100.0)
    d = np.zeros(spec.shape, np.float32)
    d[2, 5], d[0, 7], d[3, 0] = 10.0, 20.0, 30.0
    i = np.full(spec.shape, 0.5, np.float32)
    pts = unproject(d, i, spec, intensity_scale=255.0)
    assert pts.dtype == np.float32 and pts.shape == (3, 4)
    np.testing.assert_allclose(np.linalg.norm(pts[:, :3], axis=1), [20.0, 10.0, 30.0], rtol=1e-6)
    np.testing.assert_allclose(pts[:, 3], 127.5)
    elev, azim = pixel_angles(spec)
    p = pts[1]
    assert np.arctan2(p[2], np.hypot(p[0], p[1])) == pytest.approx(elev[2], abs=1e-6)
    assert np.arctan2(p[1], p[0]) == pytest.approx(azim[5], abs=1e-6)
    # re-projecting pixel-centre points lands in the same pixels
    proj = project(pts, spec, intensity_scale=255.0)
    assert proj.point_row.tolist() == [0, 2, 3] and proj.point_col.tolist() == [7, 5, 0]


def test_scan_level_helpers(synthetic_sweep):
    scan = Scan(points=synthetic_sweep.points)
    img = to_range_image(scan, SPEC)
    back = from_range_image(img, SPEC, intensity_scale=1.0, ring_from_row=True)
    assert len(back) == int((img[0] > -1).sum())
    assert back.ring is not None and back.ring.min() >= 0 and back.ring.max() <= 63
    # row-major: rings are non-decreasing
    assert np.all(np.diff(back.ring) >= 0)
    assert np.isfinite(back.points).all()


def test_beam_angle_features():
    spec = RangeImageSpec(8, 32, 3.0, -25.0, 1.45, 80.0)
    f = beam_angle_features(spec)
    assert f.shape == (32, 8, 32) and f.dtype == np.float32
    elev, azim = pixel_angles(spec)
    np.testing.assert_allclose(f[0], 0.0)  # sin(0)
    np.testing.assert_allclose(f[6], 1.0)  # cos(0)
    np.testing.assert_allclose(f[1][:, 0], np.sin(elev), atol=1e-6)
    np.testing.assert_allclose(f[12 + 3][0], np.sin(3 * azim), atol=1e-6)
    np.testing.assert_allclose(f[22 + 9][0], np.cos(9 * azim), atol=1e-6)
    assert np.all(f[1] == f[1][:, :1])  # elevation channels constant along a row


def test_bad_shapes_raise_input_error():
    with pytest.raises(InputError):
        project(np.zeros((10, 3), np.float32), SPEC)
    with pytest.raises(InputError):
        project(np.zeros((10, 4), np.float32), SPEC, intensity_scale=0.0)
    with pytest.raises(InputError):
        encode(np.zeros((32, 1024), np.float32), np.zeros((32, 1024), np.float32), SPEC)
    with pytest.raises(InputError):
        decode(np.zeros((1, 64, 1024), np.float32), SPEC)


def test_pitched_sensor_projects_in_its_own_frame():
    """Drone scans are stored levelled; projection undoes the mount pitch so rows are beams."""
    from omnilidar.data.range_image import RangeImageSpec, project, unproject
    from omnilidar.lidar.sensors import PRESETS, sensor_to_levelled

    sensor = PRESETS["drone_os64"]
    spec = RangeImageSpec.from_sensor(sensor, width=256)
    assert spec.pitch_deg == sensor.mount_pitch_deg != 0
    el = sensor.elevations_rad[:, None]
    az = np.linspace(-np.pi, np.pi, 256, endpoint=False)[None, :] + np.pi / 256
    r = 20.0
    xyz_sensor = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az),
                           np.broadcast_to(r * np.sin(el), (64, 256))], -1).reshape(-1, 3)
    pts = np.zeros((len(xyz_sensor), 4), np.float32)
    pts[:, :3] = sensor_to_levelled(xyz_sensor, sensor.mount_pitch_deg)
    res = project(pts, spec)
    assert res.mask.all(), "every beam x column pixel gets its return"
    np.testing.assert_array_equal(res.point_row, np.repeat(np.arange(64), 256))
    back = unproject(res.range_img, res.intensity_img, spec)
    assert np.abs(np.linalg.norm(back[:, :3], axis=1) - r).max() < 1e-3
    # Back in the levelled frame: the lowest beam looks down by fov_down + pitch.
    assert back[:, 2].min() < -r * np.sin(np.deg2rad(40.0))


def test_round_trip_scan_keeps_what_the_image_holds_and_carries_labels(synthetic_sweep):
    from omnilidar.data.range_image import round_trip

    scan = synthetic_sweep
    fine = RangeImageSpec.from_sensor(PRESETS["kitti_hdl64e"], width=1024)
    coarse = RangeImageSpec.from_sensor(PRESETS["kitti_hdl64e"], height=32, width=256)
    kept = {}
    for name, spec in (("fine", fine), ("coarse", coarse)):
        out = round_trip(scan, spec)
        proj = project(scan.points, spec)
        assert len(out) == int((proj.point_index_img >= 0).sum())  # one point per filled pixel
        winners = proj.point_index_img[proj.point_index_img >= 0]  # row-major
        assert np.array_equal(out.semantic, scan.semantic[winners])  # each pixel's winner's label
        assert np.array_equal(out.instance, scan.instance[winners])
        # The point comes back where its winner was, up to the pixel's angular size.
        err = np.linalg.norm(out.points[:, :3] - scan.points[winners, :3], axis=1)
        r = np.linalg.norm(scan.points[winners, :3], axis=1)
        pixel = np.hypot(np.deg2rad(28.0 / spec.height), 2 * np.pi / spec.width)
        assert np.all(err <= r * pixel + 1e-3 * r + 0.01)
        assert np.array_equal(out.ring, np.nonzero(proj.point_index_img >= 0)[0])
        kept[name] = len(out) / len(scan)
    assert kept["coarse"] < 0.1 < 0.3 < kept["fine"]  # 32 x 256 keeps a few percent of a sweep
