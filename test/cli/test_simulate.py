# SPDX-License-Identifier: Apache-2.0
"""`lompr simulate`: the bag, its ground truth, the injected faults."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from lompr_predictor.cli import main as lompr_main
from lompr_predictor.cli import simulate as simulate_cli
from lompr_predictor.data.bags import JointSamples, Recording, read_recording, write_recording
from lompr_predictor.data.loading import BagInputs, load_clean_data
from lompr_predictor.robot.chain import LomprChain
from lompr_predictor.robot.description import MEASURED_JOINTS, ROBOT_FRAME, RobotDescription
from lompr_predictor.robot.kinematics import ForwardKinematics
from lompr_predictor.robot.paths import build_cycle
from lompr_predictor.twin import Simulation, load_twin_parameters, simulate
from lompr_predictor.twin.faults import FaultSpec, inject_faults
from lompr_predictor.twin.recording import (
    ERROR_PLOT,
    GROUND_TRUTH_JSON,
    read_ground_truth,
    to_recording,
    write_simulation,
)

PARAMS = load_twin_parameters()
PERIOD_NS = 40_000_000


@pytest.fixture(scope='module')
def one_pass(description: RobotDescription) -> Simulation:
    return simulate(description, PARAMS, passes=1, seed=11)


def _run_cli(*argv: str) -> int:
    parser = argparse.ArgumentParser()
    simulate_cli.add_parser(parser.add_subparsers(dest='command'))
    args = parser.parse_args(['simulate', *argv])
    return args.run(args)


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_bag_round_trip(tmp_path: Path, description: RobotDescription,
                        one_pass: Simulation, storage: str) -> None:
    bag = write_simulation(tmp_path / 'bag', one_pass, PARAMS, description.sha256,
                           storage=storage, plot=False)
    recording = read_recording(bag)
    assert recording.joints.names == MEASURED_JOINTS
    np.testing.assert_array_equal(recording.joints.stamps, one_pass.stamps)
    np.testing.assert_array_equal(recording.joints.positions, one_pass.joints_measured)
    np.testing.assert_array_equal(recording.reference.stamps, one_pass.stamps)
    np.testing.assert_array_equal(recording.reference.positions, one_pass.reference)
    np.testing.assert_array_equal(recording.reference.orientations,
                                  np.tile([0.0, 0.0, 0.0, 1.0], (len(one_pass.stamps), 1)))
    assert recording.joints.stamps[0] == 1_700_000_000 * 10 ** 9  # the simulated clock
    assert set(np.diff(recording.joints.stamps)) == {PERIOD_NS}
    # Joints are matched by name, whatever order the reader asks for.
    reordered = read_recording(bag, joint_names=MEASURED_JOINTS[::-1])
    np.testing.assert_array_equal(reordered.joints.positions, one_pass.joints_measured[:, ::-1])


def test_joint_order_in_the_message_does_not_matter(tmp_path: Path, one_pass: Simulation) -> None:
    recording, _ = to_recording(one_pass)
    order = [4, 2, 0, 3, 1]
    shuffled = Recording(
        joints=JointSamples(stamps=recording.joints.stamps,
                            positions=recording.joints.positions[:, order],
                            names=tuple(MEASURED_JOINTS[i] for i in order)),
        reference=recording.reference)
    write_recording(tmp_path / 'shuffled', shuffled)
    np.testing.assert_array_equal(read_recording(tmp_path / 'shuffled').joints.positions,
                                  one_pass.joints_measured)


def test_a_topic_recorded_over_two_connections_is_read_whole(tmp_path: Path) -> None:
    """Another writer may give one topic several connections (two publishers, a restart):
    the messages of both are read, in stamp order after cleaning, none lost."""
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    def qos(depth: int) -> Qos:
        never = QosTime(sec=0, nsec=0)
        return Qos(history=QosHistory.KEEP_LAST, depth=depth,
                   reliability=QosReliability.RELIABLE, durability=QosDurability.VOLATILE,
                   deadline=never, lifespan=never, liveliness=QosLiveliness.AUTOMATIC,
                   liveliness_lease_duration=never, avoid_ros_namespace_conventions=False)

    store = get_typestore(Stores.ROS2_JAZZY)
    types = store.types
    time, header = types['builtin_interfaces/msg/Time'], types['std_msgs/msg/Header']
    pose, point = types['geometry_msgs/msg/Pose'], types['geometry_msgs/msg/Point']
    quaternion = types['geometry_msgs/msg/Quaternion']

    def stamp(k: int) -> Any:
        return header(stamp=time(sec=100 + k, nanosec=0), frame_id=ROBOT_FRAME)

    with Writer(tmp_path / 'two', version=9) as writer:
        joints = [writer.add_connection('/joint_states', 'sensor_msgs/msg/JointState',
                                        typestore=store, offered_qos_profiles=[qos(depth)])
                  for depth in (10, 100)]
        reference = writer.add_connection('/lompr/reference', 'geometry_msgs/msg/PoseStamped',
                                          typestore=store)
        for k in range(6):
            state = types['sensor_msgs/msg/JointState'](
                header=stamp(k), name=list(MEASURED_JOINTS), position=np.full(5, float(k)),
                velocity=np.empty(0), effort=np.empty(0))
            writer.write(joints[k % 2], k, store.serialize_cdr(state, 'sensor_msgs/msg/JointState'))
            target = types['geometry_msgs/msg/PoseStamped'](
                header=stamp(k), pose=pose(position=point(x=0.0, y=0.0, z=1.0),
                                           orientation=quaternion(x=0.0, y=0.0, z=0.0, w=1.0)))
            writer.write(reference, k, store.serialize_cdr(target, 'geometry_msgs/msg/PoseStamped'))
    recording = read_recording(tmp_path / 'two')
    assert sorted(recording.joints.stamps // 10**9) == list(range(100, 106))
    assert sorted(recording.joints.positions[:, 0]) == [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]


def test_fk_of_the_bag_is_the_ground_truth_error(tmp_path: Path, description: RobotDescription,
                                                 one_pass: Simulation) -> None:
    bag = write_simulation(tmp_path / 'bag', one_pass, PARAMS, description.sha256, plot=False)
    recording = read_recording(bag)
    truth, document = read_ground_truth(bag)
    fk = ForwardKinematics(description)  # the kinematics node's solver, sample by sample
    rows = np.arange(0, len(recording.joints.stamps), 7)
    error = np.array([fk.solve(recording.joints.positions[i]).position for i in rows]) - (
        recording.reference.positions[rows])
    np.testing.assert_allclose(error, truth['error_measured'][rows], rtol=0, atol=1e-9)
    assert document['samples'] == len(truth['stamps']) == len(one_pass.stamps)
    assert document['robot_description_sha256'] == description.sha256
    irreducible = document['irreducible_rmse_um']['1']
    assert 0.1 < irreducible['x'] < document['error_um']['measured']['x']['rms_um']


def test_same_seed_same_bag(tmp_path: Path) -> None:
    for name in ('a', 'b'):
        assert _run_cli('--out', str(tmp_path / name), '--passes', '1', '--seed', '3',
                        '--path', 'concentric', '--storage', 'sqlite3', '--nans', '2',
                        '--no-plot') == 0
    first, second = (read_recording(tmp_path / name) for name in 'ab')
    np.testing.assert_array_equal(first.joints.positions, second.joints.positions)
    np.testing.assert_array_equal(first.joints.stamps, second.joints.stamps)
    truth_a, doc_a = read_ground_truth(tmp_path / 'a')
    truth_b, doc_b = read_ground_truth(tmp_path / 'b')
    np.testing.assert_array_equal(truth_a['error_true'], truth_b['error_true'])
    assert doc_a == doc_b


def test_cli_writes_faults_and_logs_them(tmp_path: Path) -> None:
    out = tmp_path / 'faulty'
    assert _run_cli('--out', str(out), '--passes', '1', '--seed', '2', '--gaps', '3',
                    '--gap-length', '5', '--duplicates', '4', '--out-of-order', '2',
                    '--nans', '3', '--spikes', '2', '--fault-topic', 'both') == 0
    recording = read_recording(out)
    truth, document = read_ground_truth(out)
    clean = len(truth['stamps'])
    for topic, stamps in (('joint_states', recording.joints.stamps),
                          ('reference', recording.reference.stamps)):
        counts = document['faults']['injected'][topic]['counts']
        assert counts == {'gaps': 3, 'dropped_messages': 15, 'duplicates': 4,
                          'out_of_order': 2, 'nans': 3, 'spikes': 2}
        assert len(stamps) == clean - 15 + 4
    with pytest.raises(SystemExit) as refused:  # checked before the twin runs
        _run_cli('--out', str(out), '--passes', '1')
    assert refused.value.code == 2
    assert json.loads((out / GROUND_TRUTH_JSON).read_text())['passes'] == 1
    assert (out / ERROR_PLOT).read_bytes().startswith(b'\x89PNG')


def test_each_fault_is_exactly_what_it_says() -> None:
    stamps = 10 ** 18 + PERIOD_NS * np.arange(2000, dtype=np.int64)
    values = np.random.default_rng(0).uniform(0.7, 0.9, (2000, 5))
    spec = FaultSpec(gaps=4, gap_length=7, duplicates=5, out_of_order=6, nans=3, spikes=8,
                     spike_size=0.01)
    out, faulty, log = inject_faults(stamps, values, spec, np.random.default_rng(1))
    assert len(out) == 2000 - 4 * 7 + 5
    unique, counts = np.unique(out, return_counts=True)
    assert (counts == 2).sum() == 5 and counts.max() == 2
    assert sorted(unique[counts == 2]) == sorted(log.duplicated)
    assert (np.diff(out) < 0).sum() == 6
    assert (np.diff(unique) > PERIOD_NS * 1.5).sum() == 4
    assert (np.diff(unique)[np.diff(unique) > PERIOD_NS] == 8 * PERIOD_NS).all()
    assert np.isnan(faulty).any(axis=1).sum() == 3
    row_of = {int(s): i for i, s in enumerate(stamps)}
    original = values[[row_of[int(s)] for s in out]]
    spiked = np.abs(faulty - original) > 0.005
    assert spiked.sum() == 8
    assert sorted(int(s) for s in out[spiked.any(axis=1)]) == sorted(int(s[0]) for s in log.spiked)
    assert log.counts() == {'gaps': 4, 'dropped_messages': 28, 'duplicates': 5,
                            'out_of_order': 6, 'nans': 3, 'spikes': 8}


def test_too_many_faults_are_refused() -> None:
    stamps = np.arange(20, dtype=np.int64)
    with pytest.raises(ValueError, match='gaps of 10 messages do not fit'):
        inject_faults(stamps, np.zeros((20, 5)), FaultSpec(gaps=3), np.random.default_rng(0))


def test_sample_bag_is_what_its_command_makes(description: RobotDescription) -> None:
    bag = Path(__file__).resolve().parents[2] / 'bags' / 'twin_spiral_seed1_3passes'
    recording = read_recording(bag)
    truth, document = read_ground_truth(bag)
    assert (document['passes'], document['seed'], document['path']) == (3, 1, 'spiral')
    again = simulate(description, PARAMS, passes=3, seed=1)
    # Another CPU's or library's last-bit rounding (5e-17 m seen) is all that may differ; it
    # may move a reading across an encoder step, no further.
    np.testing.assert_allclose(recording.reference.positions, again.reference, rtol=0, atol=1e-12)
    np.testing.assert_allclose(truth['error_true'], again.error_true, rtol=0, atol=1e-12)
    step = [PARAMS.quantisation.length_step] * 3 + [PARAMS.quantisation.angle_step] * 2
    difference = np.abs(recording.joints.positions - again.joints_measured)
    assert (difference <= 1.01 * np.array(step)).all()
    assert (recording.joints.positions == again.joints_measured).mean() > 0.999


def test_cli_records_the_reference_preview_a_path_generator_would_publish(
        tmp_path: Path) -> None:
    """--preview K: with each sample a nav_msgs/Path of the next K references, each pose
    stamped with its instant and equal to the reference recorded for it; fewer at the end of
    the run; written in stamp order with the other topics; the inputs read as before."""
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    out = tmp_path / 'preview'
    assert _run_cli('--out', str(out), '--passes', '1', '--seed', '4', '--preview', '3',
                    '--no-plot') == 0
    recording = read_recording(out)  # the inputs, as without a preview
    reference = dict(zip(recording.reference.stamps.tolist(),
                         recording.reference.positions.tolist(), strict=True))
    typestore = get_typestore(Stores.ROS2_JAZZY)
    log_times: list[int] = []
    previews: list[Any] = []
    with Reader(out) as reader:
        assert {c.topic: c.msgtype for c in reader.connections}['/lompr/reference_preview'] \
            == 'nav_msgs/msg/Path'
        for connection, log_time, raw in reader.messages():
            log_times.append(log_time)
            if connection.topic == '/lompr/reference_preview':
                previews.append(typestore.deserialize_cdr(raw, connection.msgtype))
    assert log_times == sorted(log_times)
    stamps = recording.reference.stamps.tolist()
    assert len(previews) == len(stamps)

    def ns(stamp: Any) -> int:
        return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)

    for k, preview in enumerate(previews):
        assert ns(preview.header.stamp) == stamps[k] and preview.header.frame_id == ROBOT_FRAME
        assert [ns(p.header.stamp) for p in preview.poses] == stamps[k + 1:k + 4]
        for pose in preview.poses:
            p = pose.pose.position
            assert [p.x, p.y, p.z] == reference[ns(pose.header.stamp)]
    assert [len(p.poses) for p in previews[-4:]] == [3, 2, 1, 0]
    assert read_ground_truth(out)[1]['preview_samples'] == 3


def test_the_new_programs_record_bags_that_lompr_train_reads(
        tmp_path: Path, description: RobotDescription) -> None:
    """`lompr simulate --path K` for each program beyond the paper's three; the trainer's
    read-and-clean step gives back the ground truth's error, and `lompr train` trains on
    two programs and scores on the third."""
    bags, samples = {}, {}
    for kind in ('lissajous', 'radial', 'random'):
        bags[kind] = tmp_path / kind
        assert _run_cli('--out', str(bags[kind]), '--passes', '2', '--seed', '1', '--path',
                        kind, '--no-plot') == 0
        truth, document = read_ground_truth(bags[kind])
        samples[kind] = 2 * len(build_cycle(kind, PARAMS.path, PARAMS.sample_period, 1))
        assert document['path'] == kind and document['samples'] == samples[kind]
        clean, _ = load_clean_data(BagInputs((str(bags[kind]),)), LomprChain(description))
        np.testing.assert_array_equal(clean.stamps, truth['stamps'])  # every sample kept
        # but for a few the spike rule replaced by their neighbours' interpolation
        differs = (np.abs(clean.error - truth['error_measured'][:, :2]) > 1e-9).any(axis=1)
        assert differs.sum() == clean.counts['spike'] <= 5
    window, horizon = 8, 2
    report = tmp_path / 'report'
    assert lompr_main([
        'train', str(bags['lissajous']), str(bags['radial']), '--test-bags',
        str(bags['random']), '--out', str(tmp_path / 'model.pt'), '--report', str(report),
        '--trials', '2', '--max-epochs', '2', '--window', str(window), '--horizon',
        str(horizon), '--quiet', '--batch-sizes', '500', '--hidden-units', '4,8',
        '--workers', '1', '--restarts', '1']) == 0
    content = json.loads((report / 'report.json').read_text())
    assert content['counts']['joint_read'] == samples['lissajous'] + samples['radial']
    assert content['split']['test'] == samples['random'] - horizon - window + 1 - horizon
