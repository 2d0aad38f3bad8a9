"""``tacest record --source rosbag``: bags written with ``rosbags`` itself (ROS 1, ROS 2
sqlite3 and MCAP) from a simulated run are read back into the same run, with dropped
messages as /quality/missing and one-line errors for bad bags and mappings."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tacest.errors import TacestError
from tacest.geometry.transforms import quat_from_axis_angle, quat_to_matrix

rosbags = pytest.importorskip("rosbags")

TACEST = str(Path(sys.executable).parent / "tacest")
T0_NS = 1_700_000_000_000_000_000  # a wall-clock stamp, as a real bag has

MAPPING = """
dt = 0.01
world_frame = "world"

[[fingers]]
radius = 0.01
position = { topic = "/finger0/pose" }
force = { topic = "/finger0/wrench" }
contact = { topic = "/finger0/contact" }
normal = { topic = "/finger0/normal" }
"""

MAPPING_TF = """
dt = 0.01
world_frame = "world"

[[fingers]]
radius = 0.01
position = { tf = "finger0_tip" }
force = { topic = "/finger0/wrench" }
contact = { force_threshold = 1e-6 }
normal = { topic = "/finger0/normal" }
"""

#: the force/torque sensor frame of the TF bag: turned 30° about z from the world
SENSOR_QUAT = quat_from_axis_angle(np.array([0.0, 0.0, 1.0]), np.deg2rad(30.0))


@pytest.fixture(scope="module")
def sim_run():
    from tacest.sim.record import SimOptions
    from tacest.sim3d.record import record_sim

    run = record_sim(SimOptions(dim=3, pokes=1, seed=5, object_spec="box:0.08,0.06,0.05"))
    assert run.contact.sum() > 10  # the poke touches: contact and normals are tested
    return run


def _typestore(ros1):
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)


def write_bag(run, path, kind="ros1", drop=(), tf=False):
    """Write ``run``'s finger streams to a bag with rosbags.

    kind : "ros1" (.bag), "ros2" (sqlite3 folder) or "mcap" (ROS 2 folder, MCAP storage);
    drop : sample indices whose messages (every topic) are left out;
    tf : the fingertip as TF frame ``finger0_tip`` on /tf (world -> finger0_tip) and the
    wrench in frame ``ft_sensor`` (a /tf_static rotation of the world), instead of
    PoseStamped and a world-frame wrench.  Normals are published only where in contact.
    """
    ros1 = kind == "ros1"
    ts = _typestore(ros1)
    T = ts.types
    Time = T["builtin_interfaces/msg/Time"]

    def header(ns, frame):
        kw = {"seq": 0} if ros1 else {}
        return T["std_msgs/msg/Header"](**kw, stamp=Time(sec=ns // 10**9, nanosec=ns % 10**9), frame_id=frame)

    V3 = T["geometry_msgs/msg/Vector3"]

    def v3(v):
        return V3(x=float(v[0]), y=float(v[1]), z=float(v[2]))

    def transform(ns, parent, child, p, q):
        return T["geometry_msgs/msg/TransformStamped"](
            header=header(ns, parent), child_frame_id=child,
            transform=T["geometry_msgs/msg/Transform"](
                translation=v3(p), rotation=T["geometry_msgs/msg/Quaternion"](x=q[1], y=q[2], z=q[3], w=q[0])))

    if ros1:
        from rosbags.rosbag1 import Writer

        writer = Writer(path)
        ser = ts.serialize_ros1
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP if kind == "mcap" else
                        StoragePlugin.SQLITE3)
        ser = ts.serialize_cdr
    R_sensor = quat_to_matrix(SENSOR_QUAT)
    with writer:
        def conn(topic, typ):
            return writer.add_connection(topic, typ, typestore=ts)

        c_wrench = conn("/finger0/wrench", "geometry_msgs/msg/WrenchStamped")
        c_contact = conn("/finger0/contact", "std_msgs/msg/Bool")
        c_normal = conn("/finger0/normal", "geometry_msgs/msg/Vector3Stamped")
        if tf:
            c_tf = conn("/tf", "tf2_msgs/msg/TFMessage")
            c_static = conn("/tf_static", "tf2_msgs/msg/TFMessage")
            msg = T["tf2_msgs/msg/TFMessage"](transforms=[transform(T0_NS, "world", "ft_sensor", np.zeros(3),
                                                                     SENSOR_QUAT)])
            writer.write(c_static, T0_NS, ser(msg, "tf2_msgs/msg/TFMessage"))
        else:
            c_pose = conn("/finger0/pose", "geometry_msgs/msg/PoseStamped")
        for k in range(run.n_samples):
            if k in drop:
                continue
            ns = T0_NS + int(round(run.time[k] * 1e9))
            p = run.finger_position[k, 0]
            if tf:
                msg = T["tf2_msgs/msg/TFMessage"](transforms=[transform(ns, "world", "finger0_tip", p,
                                                                         [1.0, 0, 0, 0])])
                writer.write(c_tf, ns, ser(msg, "tf2_msgs/msg/TFMessage"))
                f, frame = R_sensor.T @ run.force[k, 0], "ft_sensor"
            else:
                pose = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=p[0], y=p[1], z=p[2]),
                                                   orientation=T["geometry_msgs/msg/Quaternion"](x=0, y=0, z=0, w=1))
                msg = T["geometry_msgs/msg/PoseStamped"](header=header(ns, "world"), pose=pose)
                writer.write(c_pose, ns, ser(msg, "geometry_msgs/msg/PoseStamped"))
                f, frame = run.force[k, 0], "world"
            msg = T["geometry_msgs/msg/WrenchStamped"](header=header(ns, frame), wrench=T["geometry_msgs/msg/Wrench"](
                force=v3(f), torque=v3(np.zeros(3))))
            writer.write(c_wrench, ns, ser(msg, "geometry_msgs/msg/WrenchStamped"))
            msg = T["std_msgs/msg/Bool"](data=bool(run.contact[k, 0]))
            writer.write(c_contact, ns, ser(msg, "std_msgs/msg/Bool"))
            if run.contact[k, 0]:
                msg = T["geometry_msgs/msg/Vector3Stamped"](header=header(ns, "world"), vector=v3(run.normal[k, 0]))
                writer.write(c_normal, ns, ser(msg, "geometry_msgs/msg/Vector3Stamped"))
    return path


def _mapping(tmp_path, text=MAPPING):
    p = tmp_path / "map.toml"
    p.write_text(text)
    return p


def _check_round_trip(run, back, missing=()):
    T = run.n_samples
    assert back.n_samples == T and back.dt == pytest.approx(0.01)
    np.testing.assert_allclose(back.time, run.time - run.time[0], atol=1e-9)
    ok = np.ones(T, bool)
    ok[list(missing)] = False
    assert np.flatnonzero(back.missing).tolist() == sorted(missing)
    np.testing.assert_allclose(back.finger_position[ok], run.finger_position[ok], atol=1e-9)
    np.testing.assert_allclose(back.force[ok], run.force[ok], atol=1e-9)
    np.testing.assert_array_equal(back.contact[ok], run.contact[ok])
    on = ok & (run.contact[:, 0] == 1)
    np.testing.assert_allclose(back.normal[on], run.normal[on], atol=1e-9)
    # placeholders at missing samples: contact 0, force 0, normal NaN, position interpolated
    assert np.all(back.contact[~ok] == 0) and np.all(back.force[~ok] == 0) and np.all(np.isnan(back.normal[~ok]))
    # (interpolated across the gap: the fingertip moves up to ~4 mm per sample on approach)
    np.testing.assert_allclose(back.finger_position[~ok], run.finger_position[~ok], atol=1e-2)


@pytest.mark.parametrize("kind", ["ros1", "ros2", "mcap"])
def test_round_trip_through_a_bag(sim_run, tmp_path, kind):
    from tacest.sensors.rosbag import record_rosbag

    bag = write_bag(sim_run, tmp_path / ("run.bag" if kind == "ros1" else "run_bag"), kind)
    back = record_rosbag(bag, _mapping(tmp_path))
    _check_round_trip(sim_run, back)


def test_dropped_messages_are_missing_samples(sim_run, tmp_path):
    from tacest.sensors.rosbag import record_rosbag

    on = np.flatnonzero(sim_run.contact[:, 0])
    drop = {20, 21, int(on[3])}  # two in a row off contact, one during the poke
    bag = write_bag(sim_run, tmp_path / "gaps.bag", "ros1", drop=drop)
    back = record_rosbag(bag, _mapping(tmp_path))
    _check_round_trip(sim_run, back, missing=drop)
    np.testing.assert_array_equal(back.missing_finger[:, 0], back.missing)


def test_tf_positions_and_a_wrench_in_a_sensor_frame(sim_run, tmp_path):
    """Fingertip from /tf, the wrench in a frame turned 30° (/tf_static), contact from
    the force: the run is back in the world frame."""
    from tacest.sensors.rosbag import record_rosbag

    bag = write_bag(sim_run, tmp_path / "tf_bag", "ros2", tf=True)
    back = record_rosbag(bag, _mapping(tmp_path, MAPPING_TF))
    np.testing.assert_allclose(back.finger_position, sim_run.finger_position, atol=1e-9)
    np.testing.assert_allclose(back.force, sim_run.force, atol=1e-9)
    want = np.linalg.norm(sim_run.force[:, 0], axis=1) > 1e-6
    np.testing.assert_array_equal(back.contact[:, 0], want)


def test_cli_writes_a_run_that_reads_back(sim_run, tmp_path):
    from tacest.io.run import read_run

    bag = write_bag(sim_run, tmp_path / "run.bag", "ros1")
    out = tmp_path / "run.h5"
    res = subprocess.run([TACEST, "record", "--source", "rosbag", str(bag), "--mapping", str(_mapping(tmp_path)),
                          "-o", str(out)], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert f"{sim_run.n_samples} samples, 0 missing (finger 0: 0)" in res.stderr
    back = read_run(out)
    assert back.source == "rosbag" and back.n_samples == sim_run.n_samples


def test_errors_name_the_bag_and_topic(sim_run, tmp_path):
    from tacest.sensors.rosbag import record_rosbag

    bag = write_bag(sim_run, tmp_path / "run.bag", "ros1")
    with pytest.raises(TacestError, match=r"run\.bag: topic /nope is not in the bag"):
        record_rosbag(bag, _mapping(tmp_path, MAPPING.replace("/finger0/pose", "/nope")))
    with pytest.raises(TacestError, match=r"run\.bag: /finger0/contact: position needs a 3-vector"):
        record_rosbag(bag, _mapping(tmp_path, MAPPING.replace('{ topic = "/finger0/pose" }',
                                                              '{ topic = "/finger0/contact" }')))
    with pytest.raises(TacestError, match=r"no transform chain from 'world' to 'finger0_tip'"):
        record_rosbag(bag, _mapping(tmp_path, MAPPING.replace('{ topic = "/finger0/pose" }',
                                                              '{ tf = "finger0_tip" }')))
    with pytest.raises(TacestError, match=r"map\.toml: fingers\[0\]\.colour: unknown key"):
        record_rosbag(bag, _mapping(tmp_path, MAPPING + 'colour = "red"\n'))
    with pytest.raises(TacestError, match=r"missing\.bag: no such bag"):
        record_rosbag(tmp_path / "missing.bag", _mapping(tmp_path))
    (tmp_path / "junk.bag").write_bytes(b"not a bag at all")
    with pytest.raises(TacestError, match=r"junk\.bag: not a readable ROS bag"):
        record_rosbag(tmp_path / "junk.bag", _mapping(tmp_path))
    # an empty topic: a bag with the connection but no message on it
    from rosbags.rosbag1 import Writer

    empty = tmp_path / "empty.bag"
    with Writer(empty) as w:
        ts = _typestore(True)
        for topic, typ in (("/finger0/pose", "geometry_msgs/msg/PoseStamped"),
                           ("/finger0/wrench", "geometry_msgs/msg/WrenchStamped"),
                           ("/finger0/contact", "std_msgs/msg/Bool"),
                           ("/finger0/normal", "geometry_msgs/msg/Vector3Stamped")):
            w.add_connection(topic, typ, typestore=ts)
    with pytest.raises(TacestError, match=r"empty\.bag: /finger0/\w+: no messages"):
        record_rosbag(empty, _mapping(tmp_path))
    # a message type tacest does not know, without a field to read
    odd = tmp_path / "odd.bag"
    with Writer(odd) as w:
        ts = _typestore(True)
        c = w.add_connection("/finger0/pose", "geometry_msgs/msg/Twist", typestore=ts)
        w.write(c, T0_NS, ts.serialize_ros1(ts.types["geometry_msgs/msg/Twist"](
            linear=ts.types["geometry_msgs/msg/Vector3"](x=0, y=0, z=0),
            angular=ts.types["geometry_msgs/msg/Vector3"](x=0, y=0, z=0)), "geometry_msgs/msg/Twist"))
        for topic, typ in (("/finger0/wrench", "geometry_msgs/msg/WrenchStamped"),
                           ("/finger0/contact", "std_msgs/msg/Bool"),
                           ("/finger0/normal", "geometry_msgs/msg/Vector3Stamped")):
            w.add_connection(topic, typ, typestore=ts)
    with pytest.raises(TacestError, match=r"odd\.bag: /finger0/pose: message type geometry_msgs/msg/Twist is not"):
        record_rosbag(odd, _mapping(tmp_path))
    res = subprocess.run([TACEST, "record", "--source", "rosbag", str(tmp_path / "missing.bag"), "--mapping",
                          str(_mapping(tmp_path)), "-o", str(tmp_path / "x.h5")], capture_output=True, text=True)
    assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1 and "missing.bag" in res.stderr


def test_the_example_mapping_reads():
    """tacest/configs/rosbag_mapping.toml, the documented example, is a valid mapping."""
    from tacest.sensors.rosbag import read_mapping

    m = read_mapping(Path(__file__).resolve().parents[1] / "tacest" / "configs" / "rosbag_mapping.toml")
    assert m.dt == 0.01 and len(m.fingers) == 1 and m.fingers[0].force.scale == -1.0
