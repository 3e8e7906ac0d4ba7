# SPDX-License-Identifier: Apache-2.0
"""A robot whose joints are named otherwise: `lompr train --joint-names` and `lompr evaluate
--joint-names` read its bags, and the nodes run with the same names (the same order rules as
kinematics_node's joint_names); a bag matching no names is one line listing those it has."""

from __future__ import annotations

from pathlib import Path

import pytest
from geometry_msgs.msg import PoseStamped, Vector3Stamped
from rclpy.parameter import Parameter
from ros_helpers import RosHarness, set_stamp
from sensor_msgs.msg import JointState
from trainer_data import ONE_EPOCH, RENAMED

from lompr_predictor.cli import main
from lompr_predictor.data.bags import Recording
from lompr_predictor.robot.description import ROBOT_FRAME
from lompr_predictor.ros.kinematics_node import KinematicsNode
from lompr_predictor.ros.predictor_node import PredictorNode

FAST = ONE_EPOCH


def test_a_bag_with_other_joint_names_is_one_line_listing_them(
        renamed: tuple[Path, Recording], tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    bag, _ = renamed
    code = main(['train', str(bag), '--out', str(tmp_path / 'm.pt'), '--report',
                 str(tmp_path / 'r'), *FAST])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1
    assert 'no joint(s) ups1, ups2, ups3, head_primary, head_secondary' in err
    assert 'its joints are a_axis, b1, b2, b3, c_axis' in err and '--joint-names' in err


@pytest.mark.faults
def test_two_branches_swapped_are_refused_as_an_implausible_error(
        renamed: tuple[Path, Recording], tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    """--joint-names with the first two branches swapped: the forward kinematics of the
    wrong joints lies far from the commanded path, which no machine's tracking error does;
    one line naming the likely causes, exit 2, before any trial."""
    bag, _ = renamed
    swapped = ['--joint-names', ','.join((RENAMED[1], RENAMED[0], *RENAMED[2:]))]
    code = main(['train', str(bag), '--out', str(tmp_path / 'm.pt'), '--report',
                 str(tmp_path / 'r'), *FAST, *swapped])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1
    assert 'of the extent of the commanded path' in err and '--joint-names' in err
    assert not (tmp_path / 'm.pt').exists() and not list((tmp_path / 'r').glob('trials/*'))


def test_joint_names_must_name_five_distinct_joints(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(['train', 'bag', '--out', 'm.pt', '--report', 'r', '--joint-names',
                 'b1,b2,b3,c_axis']) == 2
    assert 'needs 5 distinct names' in capsys.readouterr().err


@pytest.mark.slow
@pytest.mark.ros
def test_train_and_evaluate_with_joint_names_then_run_the_nodes_with_them(
        renamed: tuple[Path, Recording], tmp_path: Path, ros: RosHarness) -> None:
    bag, recording = renamed
    model = tmp_path / 'model.pt'
    names = ['--joint-names', ','.join(RENAMED)]
    assert main(['train', str(bag), '--out', str(model), '--report', str(tmp_path / 'report'),
                 *FAST, *names]) == 0
    assert main(['evaluate', str(model), str(bag), '--report', str(tmp_path / 'scored'),
                 '--quiet', *names]) == 0

    ros.add(KinematicsNode(context=ros.context, parameter_overrides=[
        Parameter('joint_names', value=list(RENAMED))]))
    ros.add(PredictorNode(context=ros.context, parameter_overrides=[
        Parameter('model_path', value=str(model)), Parameter('stale_periods', value=1000.0),
        Parameter('late_tolerance', value=60.0)]))
    compensations = ros.collect('/lompr/compensation', Vector3Stamped, 100)
    joints, references = publishers = [
        ros.node.create_publisher(kind, topic, 100)
        for topic, kind in (('/joint_states', JointState), ('/lompr/reference', PoseStamped))]
    for publisher in publishers:
        ros.wait_for_subscribers(publisher)
    ros.wait_for_publishers('/lompr/compensation')
    for k in range(20):
        stamp = int(recording.joints.stamps[k])
        reference = PoseStamped()
        reference.header.frame_id = ROBOT_FRAME
        set_stamp(reference, stamp)
        x, y, z = map(float, recording.reference.positions[k])
        reference.pose.position.x, reference.pose.position.y, reference.pose.position.z = x, y, z
        reference.pose.orientation.w = 1.0
        references.publish(reference)
        message = JointState(name=list(RENAMED),
                             position=[float(v) for v in recording.joints.positions[k]])
        set_stamp(message, stamp)
        joints.publish(message)
        ros.spin_for(0.01)
    ros.spin_until(lambda: len(compensations) > 0, what='compensations from the renamed joints')
