"""``tacest export`` as a user meets it: the files load in MuJoCo, yourdfpy and trimesh
with the estimate's mass, inertia and geometry, say what is a prior, and a recorded
run replayed in MuJoCo against the exported object follows the trajectory.

The estimates are built by hand (tacest.io.estimate.Estimate) so no test runs the
estimator; the replay test simulates one short 3-D poke (~2 s).
"""

import json
import re
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from tacest.geometry.polytope import box_vertices_3d, polytope_inertia
from tacest.geometry.transforms import quat_from_axis_angle, quat_to_matrix, transform_points
from tacest.io.estimate import Estimate, RunEstimate, write_estimate

TACEST = str(Path(sys.executable).parent / "tacest")

BOX = (0.10, 0.06, 0.04)  # m
MASS = 0.3  # kg


def _tacest(*args, cwd=None):
    return subprocess.run([TACEST, *map(str, args)], capture_output=True, text=True, timeout=120, cwd=cwd)


def _inertia():
    """A box's inertia turned by 20° about z: off-diagonal terms that a writer could drop."""
    R = quat_to_matrix(quat_from_axis_angle(np.array([0.0, 0.0, 1.0]), np.deg2rad(20.0)))
    return R @ polytope_inertia(box_vertices_3d(BOX), MASS) @ R.T


def _estimate3(T=30, **params) -> Estimate:
    V = box_vertices_3d(BOX)
    pose = np.zeros((T, 7))
    pose[:, 0] = np.linspace(0.0, 0.05, T)
    pose[:, 2] = BOX[2] / 2
    pose[:, 3] = 1.0
    p = {"mass": MASS, "inertia": _inertia(), "friction_ground": 0.4, "friction_finger": 0.3, **params}
    return Estimate(dim=3, shape="box", vertices=V, params=p,
                    runs=[RunEstimate(pose=pose, velocity=np.zeros((T, 6)), source_file="run.h5")],
                    identifiable={"mass": False, "inertia": False, "friction_ground": True, "friction_finger": True},
                    std={"friction_ground": 0.05}, solver_status="Solve_Succeeded", success=True)


def _estimate2(T=20) -> Estimate:
    V = np.array([[-0.05, -0.02], [0.05, -0.02], [0.05, 0.02], [-0.05, 0.02]])
    pose = np.zeros((T, 3))
    pose[:, 0] = np.linspace(0, 0.03, T)
    pose[:, 1] = 0.02
    pose[:, 2] = np.linspace(0, 0.3, T)
    return Estimate(dim=2, shape="box", vertices=V, params={"mass": 0.2, "inertia": 2e-4, "friction_ground": 0.5,
                                                            "friction_finger": 0.3, "restitution.e": 0.4},
                    runs=[RunEstimate(pose=pose, velocity=np.zeros((T, 3)))],
                    identifiable={"mass": True, "inertia": True}, solver_status="Solve_Succeeded", success=True)


@pytest.fixture
def est3_file(tmp_path):
    path = tmp_path / "est3.h5"
    write_estimate(_estimate3(), path)
    return path


def _full_inertia(model, body):
    """(3, 3) inertia about the COM in the body frame from MuJoCo's principal moments."""
    R = quat_to_matrix(np.array(model.body_iquat[body]))
    return R @ np.diag(model.body_inertia[body]) @ R.T


def _comment(text):
    return " ".join(re.findall(r"<!--(.*?)-->", text, flags=re.S))


# ---------------------------------------------------------------------------------
# MJCF


def test_mjcf_loads_in_mujoco_with_mass_inertia_geometry_friction_and_keys(est3_file, tmp_path):
    import mujoco

    out = tmp_path / "box.xml"
    res = _tacest("export", est3_file, "-o", out)
    assert res.returncode == 0, res.stderr
    model = mujoco.MjModel.from_xml_path(str(out))
    body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "object")
    assert model.body_mass[body] == pytest.approx(MASS, rel=1e-9)
    np.testing.assert_allclose(_full_inertia(model, body), _inertia(), rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(model.body_ipos[body], 0.0, atol=1e-12)  # the body frame is at the COM
    assert model.nkey == 30
    est = _estimate3()
    np.testing.assert_allclose(model.key_qpos[7], est.runs[0].pose[7], atol=1e-12)
    # geometry: the collision mesh at keyframe 7 is where the estimate puts the box
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 7)
    mujoco.mj_forward(model, data)
    geom = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "object")
    mesh = int(model.geom_dataid[geom])
    a, n = int(model.mesh_vertadr[mesh]), int(model.mesh_vertnum[mesh])
    verts = np.array(model.mesh_vert[a:a + n]) @ np.array(data.geom_xmat[geom]).reshape(3, 3).T + data.geom_xpos[geom]
    want = transform_points(est.runs[0].pose[7], est.vertices, 3)
    dist = np.linalg.norm(verts[:, None, :] - want[None, :, :], axis=-1)
    assert n == 8 and np.max(np.min(dist, axis=1)) < 1e-6 and np.max(np.min(dist, axis=0)) < 1e-6
    assert model.geom_friction[geom][0] == pytest.approx(0.4)
    # the comment block says where numbers come from and which are priors
    text = _comment(out.read_text())
    assert re.search(r"mass 0\.3 kg \(/params mass\): NOT IDENTIFIABLE", text)
    assert "friction_ground 0.4" in text and "estimated from the data, one sigma 0.05" in text


def test_mjcf_friction_holds_for_fingers_and_ground_by_priority(est3_file, tmp_path):
    """A fingertip of class tacest_finger pressed on the object: MuJoCo's contact takes
    the finger friction; the object on the ground: the ground friction."""
    import mujoco

    from tacest.export.replay import add_fingers

    out = tmp_path / "box.xml"
    assert _tacest("export", est3_file, "-o", out).returncode == 0
    model = mujoco.MjModel.from_xml_string(add_fingers(out.read_text(), [0.01]))
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    data.qpos[2] -= 1e-4  # 0.1 mm into the ground
    data.mocap_pos[0] = [0.0, 0.0, BOX[2] + 0.0095]  # 0.5 mm into the top face
    mujoco.mj_forward(model, data)
    mu = {}
    for i in range(data.ncon):
        c = data.contact[i]
        names = {mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g) for g in c.geom}
        mu["finger" if any(n.startswith("tacest_replay") for n in names) else "ground"] = c.friction[0]
    assert mu["finger"] == pytest.approx(0.3) and mu["ground"] == pytest.approx(0.4)


def test_mjcf_rounded_edges_rest_at_the_outer_size(tmp_path):
    """edge_radius r as the margin of the inner box: it rests with its centre at the
    outer half height (the estimate's box is the outer size), not r lower."""
    import mujoco

    r = 0.005
    est = _estimate3(edge_radius=r)
    est.runs[0].pose[:, 2] += 0.002  # let it drop onto the ground
    path = tmp_path / "e.h5"
    write_estimate(est, path)
    out = tmp_path / "round.xml"
    assert _tacest("export", path, "-o", out).returncode == 0
    model = mujoco.MjModel.from_xml_path(str(out))
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    for _ in range(int(0.5 / model.opt.timestep)):
        mujoco.mj_step(model, data)
    assert data.qpos[2] == pytest.approx(BOX[2] / 2, abs=2e-4)
    assert "edge_radius 0.005 m (as the geom margin on the inner box)" in _comment(out.read_text())


def test_mjcf_keyframes_are_subsampled_and_trajectory_csv(est3_file, tmp_path):
    import mujoco

    out, csv_path = tmp_path / "k.xml", tmp_path / "traj.csv"
    res = _tacest("export", est3_file, "-o", out, "--keyframes", "5", "--trajectory", csv_path)
    assert res.returncode == 0, res.stderr
    model = mujoco.MjModel.from_xml_path(str(out))
    assert model.nkey == 5
    pose = _estimate3().runs[0].pose
    np.testing.assert_allclose(model.key_qpos[-1], pose[-1], atol=1e-12)
    rows = np.genfromtxt(csv_path, delimiter=",", names=True)
    assert rows.shape == (30,) and rows.dtype.names == ("sample", "time", "x", "y", "z", "qw", "qx", "qy", "qz")
    np.testing.assert_allclose(rows["x"], pose[:, 0])
    assert np.all(np.isnan(rows["time"]))  # the run file is not there: time unknown, said so
    assert "sample times unknown" in _comment(out.read_text())


# ---------------------------------------------------------------------------------
# URDF, SDF, meshes


@pytest.mark.filterwarnings("ignore:.*Scene.dump:DeprecationWarning")  # inside yourdfpy
def test_urdf_loads_in_yourdfpy_with_mass_inertia_and_mesh(est3_file, tmp_path):
    yourdfpy = pytest.importorskip("yourdfpy")
    out = tmp_path / "model" / "box.urdf"
    out.parent.mkdir()
    res = _tacest("export", est3_file, "-o", out)
    assert res.returncode == 0, res.stderr
    assert (out.parent / "box.stl").is_file()
    robot = yourdfpy.URDF.load(str(out), build_collision_scene_graph=True,
                                 load_collision_meshes=True)  # meshes relative to the URDF
    inertial = robot.link_map["object"].inertial
    assert inertial.mass == pytest.approx(MASS)
    np.testing.assert_allclose(inertial.inertia, _inertia(), rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(inertial.origin, np.eye(4))
    np.testing.assert_allclose(robot.scene.bounds, [[-b / 2 for b in BOX], [b / 2 for b in BOX]], atol=1e-7)
    coll = robot.collision_scene.to_geometry()
    assert coll.volume == pytest.approx(np.prod(BOX), rel=1e-6)  # STL stores float32
    assert "NOT IDENTIFIABLE" in _comment(out.read_text())


def test_sdf_has_link_inertia_friction_and_relative_mesh(est3_file, tmp_path):
    out = tmp_path / "box.sdf"
    assert _tacest("export", est3_file, "-o", out).returncode == 0
    root = ET.parse(out).getroot()
    link = root.find("model/link")
    assert float(link.find("inertial/mass").text) == pytest.approx(MASS)
    I = _inertia()
    assert float(link.find("inertial/inertia/ixy").text) == pytest.approx(I[0, 1])
    assert float(link.find("collision/surface/friction/ode/mu").text) == pytest.approx(0.4)
    uri = link.find("collision/geometry/mesh/uri").text
    assert uri == "box.stl" and (tmp_path / uri).is_file()


@pytest.mark.parametrize("fmt", ["obj", "stl", "glb"])
def test_meshes_hold_the_hull_and_a_physics_sidecar(est3_file, tmp_path, fmt):
    import trimesh

    out = tmp_path / f"box.{fmt}"
    assert _tacest("export", est3_file, "-o", out).returncode == 0
    mesh = trimesh.load(out, force="mesh")
    assert mesh.is_watertight and mesh.volume == pytest.approx(np.prod(BOX), rel=1e-6)
    side = json.loads((tmp_path / "box.physics.json").read_text())
    assert side["mass"] == pytest.approx(MASS) and side["identifiable"]["mass"] is False
    np.testing.assert_allclose(side["inertia"], _inertia())
    if fmt == "obj":
        assert out.read_text().startswith("# tacest export of")


# ---------------------------------------------------------------------------------
# 2-D estimates


def test_2d_estimate_is_extruded_to_the_stated_depth(tmp_path):
    import mujoco

    path = tmp_path / "e2.h5"
    write_estimate(_estimate2(), path)
    out = tmp_path / "e2.xml"
    res = _tacest("export", path, "-o", out, "--depth", "0.03")
    assert res.returncode == 0, res.stderr
    model = mujoco.MjModel.from_xml_path(str(out))
    body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "object")
    I = _full_inertia(model, body)
    assert I[1, 1] == pytest.approx(2e-4, rel=1e-9)  # the planar inertia, about y
    # uniform density along the depth: Ixx = ∫z² + m d²/12 with ∫x² : ∫z² as a 0.1 x 0.04 plate
    sxx, szz = 2e-4 * 0.1 ** 2 / (0.1 ** 2 + 0.04 ** 2), 2e-4 * 0.04 ** 2 / (0.1 ** 2 + 0.04 ** 2)
    assert I[0, 0] == pytest.approx(szz + 0.2 * 0.03 ** 2 / 12, rel=1e-6)
    assert I[2, 2] == pytest.approx(sxx + 0.2 * 0.03 ** 2 / 12, rel=1e-6)
    geom = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "object")
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, model.nkey - 1)
    mujoco.mj_forward(model, data)
    # the last pose turns the plate by 0.3 rad counter-clockwise in x-y: its +x end rises in z
    R = np.array(data.xmat[body]).reshape(3, 3)
    assert R[2, 0] == pytest.approx(np.sin(0.3)) and np.linalg.det(R) == pytest.approx(1.0)
    assert model.geom_solref[geom][1] < 1.0  # restitution as a damping ratio below critical
    text = _comment(out.read_text())
    assert "ASSUMPTION: the depth 0.03 m is not estimated" in text
    assert "restitution 0.4" in text


# ---------------------------------------------------------------------------------
# errors


def test_export_errors_are_one_line(est3_file, tmp_path):
    res = _tacest("export", est3_file, "-o", tmp_path / "a.xml", "--depth", "0.1")
    assert res.returncode == 2 and "2-D estimates" in res.stderr and len(res.stderr.strip().splitlines()) == 1
    res = _tacest("export", est3_file, "-o", tmp_path / "a.dae")
    assert res.returncode == 2 and "--format" in res.stderr and "Traceback" not in res.stderr
    res = _tacest("export", tmp_path / "missing.h5", "-o", tmp_path / "a.xml")
    assert res.returncode == 2 and "missing.h5" in res.stderr and "Traceback" not in res.stderr


# ---------------------------------------------------------------------------------
# replay, the way a user checks an export


def test_replay_of_a_recorded_poke_follows_the_trajectory(tmp_path):
    """Export the TRUE object of a simulated 3-D poke (an ideal estimate: truth shape,
    mass, inertia, friction and trajectory) and replay the recorded finger motion against
    it.  What remains is the replay's own error: mocap fingertips on the measured (noisy,
    0.1 mm) positions instead of the simulator's force-limited drive, and the export's
    geometry and contact settings.  Bound 5 mm over the poke: half the 1 cm target for a
    real estimate (docs/export.md), ~10x what this replay measures (~0.5 mm), far below
    the centimetres the object moves, so a wrong frame, mass or friction fails it."""
    from tacest.export.formats import mjcf_string
    from tacest.export.model import body_from_estimate
    from tacest.export.replay import replay_estimate
    from tacest.sim.record import SimOptions
    from tacest.sim3d.record import record_sim

    run = record_sim(SimOptions(dim=3, pokes=1, seed=5, object_spec="box:0.08,0.06,0.05"))
    tr = run.truth
    T = run.n_samples
    est = Estimate(dim=3, shape="box", vertices=tr.vertices,
                   params={"mass": tr.mass, "inertia": tr.inertia, "friction_ground": tr.friction_ground,
                           "friction_finger": tr.friction_finger},
                   runs=[RunEstimate(pose=tr.pose, velocity=np.zeros((T, 6)))])
    moved = float(np.max(np.linalg.norm(tr.pose[:, :3] - tr.pose[0, :3], axis=1)))
    assert moved > 0.01  # the poke moves the object: the test can fail
    xml = mjcf_string(body_from_estimate(est))
    res = replay_estimate(xml, run, est)
    s = res.summary()
    assert s["pokes"] == 1 and s["position_max"] < 5e-3, s
    # a wrong ground friction (the box tips instead of sliding) fails the same bound
    est.params["friction_ground"] = 1.5
    bad = replay_estimate(mjcf_string(body_from_estimate(est)), run, est).summary()
    assert bad["position_max"] > 5e-3, (bad, s)
