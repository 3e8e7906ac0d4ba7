# SPDX-License-Identifier: Apache-2.0
"""ros.launch_site: what the site's params file gives the nodes this package does not own
(robot_state_publisher, rviz2): its sections matched as rcl matches them, each setting an
argument given, else the site's, else the packaged default; a bad file in one line."""

from __future__ import annotations

from pathlib import Path

import pytest

from lompr_predictor.errors import LomprError
from lompr_predictor.robot.description import CELL_FRAME, default_description_path
from lompr_predictor.ros.launch_site import root_link, site_parameters, view_settings
from lompr_predictor.twin.arm import arm_description_path

ROOT = Path(__file__).resolve().parents[2]


def test_site_parameters_follow_rcl_keys_and_bad_files_are_one_line(tmp_path: Path) -> None:
    site = tmp_path / 'site.yaml'
    site.write_text("""
/**:
  ros__parameters: {frame_prefix: a/, hardware_id: h}
/cell1/kinematics_node:
  ros__parameters: {frame_prefix: b/}
/**/predictor_node:
  ros__parameters: {frame_prefix: c/}
""")
    assert site_parameters(str(site), 'cell1') == {'frame_prefix': 'b/', 'hardware_id': 'h'}
    assert site_parameters(str(site), '/cell2') == {'frame_prefix': 'a/', 'hardware_id': 'h'}
    assert site_parameters(str(site), '', 'predictor_node')['frame_prefix'] == 'c/'
    assert site_parameters('') == {}
    site.write_text('- a list\n')
    with pytest.raises(LomprError, match=f'^params_file {site}: not a mapping of node names$'):
        site_parameters(str(site))
    with pytest.raises(LomprError, match='2 root links, needs one'):
        root_link('<robot name="r"><link name="a"/><link name="b"/></robot>', 'r.urdf')
    assert root_link((ROOT / 'lompr_predictor/description/lompr.urdf').read_text(),
                     'lompr.urdf') == CELL_FRAME


def test_the_view_takes_an_argument_else_the_sites_file_else_the_package(
        tmp_path: Path) -> None:
    site = tmp_path / 'site.yaml'
    site.write_text(f"""
/**/kinematics_node:
  ros__parameters: {{frame_prefix: site/, robot_description_file: {arm_description_path()}}}
""")
    packaged = default_description_path()
    from_site = view_settings(str(site), 'cell1', '', '', packaged)
    assert (from_site.frame_prefix, from_site.fixed_frame) == ('site/', 'site/arm_base')
    assert from_site.robot_description == arm_description_path().read_text()
    given = view_settings(str(site), 'cell1', str(packaged), 'cell9/', packaged)
    assert (given.frame_prefix, given.fixed_frame) == ('cell9/', f'cell9/{CELL_FRAME}')
    assert given.robot_description == packaged.read_text()
    default = view_settings('', '', '', '', packaged)
    assert (default.frame_prefix, default.fixed_frame) == ('', CELL_FRAME)
    with pytest.raises(LomprError, match=r'^cannot read robot description /nonexistent\.urdf'):
        view_settings('', '', '/nonexistent.urdf', '', packaged)
