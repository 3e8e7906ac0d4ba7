# SPDX-License-Identifier: Apache-2.0
"""Two robots on one network: both nodes started in a namespace with a params file keyed
/**/<node>: move their relative topics into it and take the file's parameters; their
diagnostics are named as diagnostic_updater names them (the node's name, or with
diagnostic_updater.use_fqn its fully qualified name) and carry the robot's name or the
hardware_id given."""

from __future__ import annotations

from pathlib import Path

import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, Vector3Stamped
from model_helpers import save_constant
from ros_helpers import RosHarness, latest_status, set_stamp, start_executable, stop_process
from sensor_msgs.msg import JointState

from lompr_predictor.robot.description import MEASURED_JOINTS, ROBOT_FRAME
from lompr_predictor.ros.kinematics_node import KinematicsNode
from lompr_predictor.ros.predictor_node import PredictorNode

pytestmark = pytest.mark.ros
NAMESPACE = '/cell1'
CONFIG = Path(__file__).resolve().parents[2] / 'lompr_predictor' / 'config'


def test_both_nodes_in_a_namespace_with_a_params_file(ros: RosHarness, tmp_path: Path) -> None:
    model = save_constant(tmp_path / 'model.pt', (1e-5, -2e-5))
    params = tmp_path / 'site.yaml'
    params.write_text(f"""
/**/kinematics_node:
  ros__parameters:
    warm_start_max_gap: 0.25
    diagnostics_period: 0.1
    hardware_id: cell1_lompr
/**/predictor_node:
  ros__parameters:
    model_path: {model}
    max_compensation_step: 0.00004
    diagnostics_period: 0.1
    stale_periods: 1000.0
    late_tolerance: 60.0
    diagnostic_updater.use_fqn: true
""")
    def cli_args(node: str) -> list[str]:
        """As the launch file passes them: the packaged defaults, then the site's."""
        files = [CONFIG / f'{node}.yaml', params]
        return ['--ros-args', *(part for path in files for part in ('--params-file', str(path)))]

    kinematics = ros.add(KinematicsNode(context=ros.context, namespace=NAMESPACE,
                                        cli_args=cli_args('kinematics_node')))
    predictor = ros.add(PredictorNode(context=ros.context, namespace=NAMESPACE,
                                      cli_args=cli_args('predictor_node')))
    assert kinematics.settings.warm_start_max_gap == 0.25
    assert predictor.settings.max_compensation_step == 0.00004
    assert predictor.lifecycle_state == 'active'

    end_poses = ros.collect(f'{NAMESPACE}/lompr/end_pose', PoseStamped, 100)
    compensations = ros.collect(f'{NAMESPACE}/lompr/compensation', Vector3Stamped, 100)
    diagnostics = ros.collect('/diagnostics', DiagnosticArray, 100)
    joints = ros.node.create_publisher(JointState, f'{NAMESPACE}/joint_states', 100)
    references = ros.node.create_publisher(PoseStamped, f'{NAMESPACE}/lompr/reference', 100)
    ros.wait_for_subscribers(joints)
    ros.wait_for_subscribers(references)
    ros.wait_for_publishers(f'{NAMESPACE}/lompr/compensation')
    topics = {name for name, _ in ros.node.get_topic_names_and_types()}
    assert '/lompr/end_pose' not in topics and '/joint_states' not in topics

    start_ns = 1_700_000_000 * 10**9
    for k in range(12):
        stamp = start_ns + k * 40_000_000
        message = JointState(name=list(MEASURED_JOINTS),
                             position=[0.8, 0.8, 0.8, 0.0, 0.0])
        set_stamp(message, stamp)
        reference = PoseStamped()
        reference.header.frame_id = ROBOT_FRAME
        set_stamp(reference, stamp)
        reference.pose.position.z = 1.0
        references.publish(reference)
        joints.publish(message)
        wanted = k + 1
        ros.spin_until(lambda: len(end_poses) >= wanted, what=f'end pose {k}')  # noqa: B023
    ros.spin_until(lambda: len(compensations) > 0, what='a compensation in the namespace')

    ros.spin_until(lambda: latest_status(diagnostics, '/cell1/predictor_node: model') is not None
                   and latest_status(diagnostics, 'kinematics_node: joint states')
                   is not None, what='status names')
    hardware = {status.name.split(':')[0]: status.hardware_id for array in diagnostics
                for status in array.status}
    assert hardware == {'/cell1/predictor_node': 'lompr', 'kinematics_node': 'cell1_lompr'}


@pytest.mark.faults
def test_the_pipeline_takes_node_prefixed_parameters_in_a_namespace(
        ros: RosHarness, tmp_path: Path) -> None:
    """`lompr_pipeline --ros-args -r __ns:=/cell1 -p predictor_node:model_path:=M`, as
    documented: each node takes its own prefixed parameters in a namespace too (rcl alone
    matches a node prefix in the root namespace only)."""
    model = save_constant(tmp_path / 'model.pt', (1e-5, -2e-5))
    urdf = tmp_path / 'calibrated.urdf'
    urdf.write_bytes((CONFIG.parent / 'description' / 'lompr.urdf').read_bytes())
    diagnostics = ros.collect('/diagnostics', DiagnosticArray, 100)
    process = start_executable(
        'pipeline', '-r', f'__ns:={NAMESPACE}', '-p', f'predictor_node:model_path:={model}',
        '-p', f'kinematics_node:robot_description_file:={urdf}',
        '-p', 'predictor_node:diagnostics_period:=0.2')
    names = ('predictor_node: model', 'kinematics_node: forward kinematics')

    def both_or_exited() -> bool:
        statuses = [latest_status(diagnostics, name) for name in names]
        return None not in statuses or process.poll() is not None

    try:
        ros.spin_until(both_or_exited, timeout=60.0, what='the statuses of both nodes')
        assert process.poll() is None
        model_status, kinematics = (latest_status(diagnostics, name) for name in names)
        assert model_status is not None and model_status['path'] == str(model)
        assert kinematics is not None and kinematics['robot_description'] == str(urdf)
    finally:
        code, _ = stop_process(process)
    assert code == 0
