"""Dome calibration: the image -> dome -> normal model, its JSON file, and the normal's sign."""

import json

import numpy as np
import pytest

from tacest.errors import TacestError
from tacest.sensors.dome import DomeCalibration, calibration_from_dict, load_calibration

#: Rotations used below, written out by hand (columns = finger axes in the world).
#: 3-D: finger axis z_f = world -z (pointing down), x_f = world x, y_f = world -y.
R_DOWN = np.array([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]])
#: 2-D: z_f = world +x, x_f = world +y, y_f = world +z (out of the plane).
R_SIDE = np.array([[0.0, 0, 1], [1, 0, 0], [0, 1, 0]])

S45 = np.sqrt(0.5)


def _calib(**kw):
    d = dict(image_size=(640, 480), center_px=np.array([320.0, 240.0]), rim_radius_px=200.0,
             dome_radius_m=0.01, rotation_world_from_finger=R_DOWN)
    d.update(kw)
    return DomeCalibration(**d)


def test_image_to_finger_normal_equidistant_and_orthographic():
    c = _calib()
    assert np.allclose(c.finger_normal([320, 240]), [0, 0, 1])  # apex
    assert np.allclose(c.finger_normal([520, 240]), [1, 0, 0])  # rim, +u: polar 90 deg
    assert np.allclose(c.finger_normal([320, 340]), [0, S45, S45])  # half way, +v: polar 45 deg
    o = _calib(projection="orthographic")
    # sin(theta) = rho: rho = 0.5 -> theta = 30 deg
    assert np.allclose(o.finger_normal([220, 240]), [-0.5, 0, np.sqrt(0.75)])
    # the inverse maps back (both models)
    uv = np.array([[400.0, 300.0], [250.0, 120.0], [320.0, 240.0]])
    for cal in (c, o):
        assert np.allclose(cal.pixel_of_finger_direction(cal.finger_normal(uv)), uv)


def test_object_normal_sign_at_apex_is_minus_finger_axis():
    """Indentation at the apex: the object normal points from the object into the finger,
    i.e. against the finger's axis (which points out through the apex)."""
    c = _calib()
    finger_axis_world = R_DOWN @ [0, 0, 1]  # (0, 0, -1): the finger points down
    n, inplane = c.object_normal([320, 240])
    assert np.allclose(n, -finger_axis_world) and np.allclose(n, [0, 0, 1])
    assert inplane == 1
    # 45 deg off the apex towards +u (finger x = world x): n_f = (s, 0, s) -> world (s, 0, -s)
    n, _ = c.object_normal([320 + 100, 240])
    assert np.allclose(n, [-S45, 0, S45])


def test_object_normal_2d_projects_and_renormalises():
    c = _calib(rotation_world_from_finger=R_SIDE)
    n, inplane = c.object_normal([320, 240], dim=2)  # apex: finger axis = world +x
    assert np.allclose(n, [-1, 0]) and np.allclose(inplane, 1)
    n, inplane = c.object_normal([420, 240], dim=2)  # polar 45 towards +u = world +y
    assert np.allclose(n, [-S45, -S45])
    # polar 30 deg towards +v = out of the plane: in-plane part is cos 30 of (-1, 0)
    n, inplane = c.object_normal([320, 240 + 200 / 3], dim=2)
    assert np.allclose(n, [-1, 0]) and np.isclose(inplane, np.cos(np.pi / 6))
    # per-sample rotations broadcast
    n, _ = c.object_normal(np.array([[320, 240], [320, 240]]), np.stack([R_SIDE, R_DOWN]), dim=3)
    assert np.allclose(n, [[-1, 0, 0], [0, 0, 1]])


def test_json_round_trip(tmp_path):
    c = _calib(projection="orthographic", rim_polar_angle_deg=80.0, finger_radius_m=0.011)
    p = tmp_path / "calib.json"
    c.save(p)
    d = load_calibration(p)
    assert d.image_size == (640, 480) and d.projection == "orthographic"
    assert np.allclose(d.center_px, c.center_px) and d.finger_radius == 0.011
    assert np.allclose(d.rotation_world_from_finger, R_DOWN)
    # defaults: hemisphere, equidistant, finger radius = dome radius, no rotation
    m = calibration_from_dict({"image_size": [64, 48], "center_px": [32, 24], "rim_radius_px": 20,
                               "dome_radius_m": 0.02})
    assert m.projection == "equidistant" and m.rim_polar_angle_deg == 90 and m.finger_radius == 0.02
    assert m.rotation_world_from_finger is None


GOOD = {"image_size": [64, 48], "center_px": [32, 24], "rim_radius_px": 20, "dome_radius_m": 0.02}


@pytest.mark.parametrize("change, message", [
    ({"rim_radius_px": None}, "missing key 'rim_radius_px'"),
    ({"rim_radus_px": 3}, "rim_radus_px: unknown key"),
    ({"dome_radius_m": -1}, "dome_radius_m: must be > 0"),
    ({"center_px": [1, 2, 3]}, "center_px: expected 2"),
    ({"projection": "pinhole"}, "projection: expected one of"),
    ({"rotation_world_from_finger": [[1, 0, 0], [0, 1, 0], [0, 0, -1]]}, "not a rotation"),
    ({"rotation_world_from_finger": [[1, 0], [0, 1]]}, "3x3"),
    ({"version": 2}, "unknown version"),
])
def test_bad_calibration_is_one_clear_line(tmp_path, change, message):
    d = dict(GOOD)
    for k, v in change.items():
        if v is None:
            d.pop(k)
        else:
            d[k] = v
    p = tmp_path / "c.json"
    p.write_text(json.dumps(d))
    with pytest.raises(TacestError, match=message) as exc:
        load_calibration(p)
    assert "\n" not in str(exc.value) and str(p) in str(exc.value)


def test_not_json(tmp_path):
    p = tmp_path / "c.json"
    p.write_text("{oops")
    with pytest.raises(TacestError, match="not valid JSON"):
        load_calibration(p)


def test_rotation_is_reorthonormalised():
    m = calibration_from_dict({**GOOD, "rotation_world_from_finger": [[0.7071, -0.7071, 0], [0.7071, 0.7071, 0],
                                                                     [0, 0, 1]]})
    R = m.rotation_world_from_finger
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-12)
