# SPDX-License-Identifier: Apache-2.0
"""What the site's params file and the launch arguments give the nodes this package does
not own: robot_state_publisher and rviz2 read no params file keyed by our nodes, so the
frame prefix and URDF the site set for kinematics_node are read out of it here
(launch/lompr_view.launch.py calls this at launch time). ROS-free."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from xml.etree import ElementTree

import yaml

from lompr_predictor.errors import LomprError

#: The node whose section of the site's file speaks for the drawing: it publishes the joint
#: states robot_state_publisher draws.
SITE_NODE = 'kinematics_node'


@dataclass(frozen=True)
class ViewSettings:
    """robot_state_publisher's URDF text and frame prefix, and rviz2's fixed frame."""

    robot_description: str
    frame_prefix: str
    fixed_frame: str


def _key_matches(key: str, node: str, namespace: str) -> bool:
    """Whether a params file key (`/**/node`, `/ns/node`, `node`, `/**`) applies to `node`
    in `namespace`, as rcl's wildcards `**` and `*` match."""
    pattern = key if key.startswith('/') else f'/{key}'
    regex = re.escape(pattern).replace(r'/\*\*', '(/.*)?').replace(r'\*', '[^/]*')
    return re.fullmatch(regex, f"/{namespace.strip('/')}/{node}".replace('//', '/')) is not None


def site_parameters(params_file: str, namespace: str = '',
                    node: str = SITE_NODE) -> dict[str, Any]:
    """The parameters a site's params file gives `node` in `namespace` (later sections over
    earlier ones); {} for no file."""
    if not params_file:
        return {}
    try:
        document = yaml.safe_load(Path(params_file).read_text())
    except (OSError, yaml.YAMLError) as err:
        raise LomprError(f'params_file {params_file}: cannot read it ({err})') from err
    if not isinstance(document, dict):
        raise LomprError(f'params_file {params_file}: not a mapping of node names')
    found: dict[str, Any] = {}
    for key, section in document.items():
        if _key_matches(str(key), node, namespace) and isinstance(section, dict):
            found.update(section.get('ros__parameters') or {})
    return found


def root_link(urdf: str, source: str) -> str:
    """The URDF's root link (the one no joint is the child of): the frame the whole robot
    hangs from, the one a view fixes."""
    try:
        robot = ElementTree.fromstring(urdf)
    except ElementTree.ParseError as err:
        raise LomprError(f'robot description {source}: not XML ({err})') from err
    children = {child.get('link') for child in robot.iter('child')}
    roots = [link.get('name') for link in robot.findall('link')
             if link.get('name') not in children]
    if len(roots) != 1:
        raise LomprError(f'robot description {source}: {len(roots)} root links, needs one')
    return str(roots[0])


def view_settings(params_file: str, namespace: str, robot_description_file: str,
                  frame_prefix: str, packaged_description: Path) -> ViewSettings:
    """robot_state_publisher's and rviz2's settings: each an argument given, else the site's
    file (its kinematics_node section), else the packaged default; the fixed frame is the
    URDF's root link, prefixed."""
    site = site_parameters(params_file, namespace)
    description = Path(robot_description_file or site.get('robot_description_file')
                       or packaged_description)
    prefix = frame_prefix or str(site.get('frame_prefix') or '')
    try:
        urdf = description.read_text()
    except OSError as err:
        raise LomprError(f'cannot read robot description {description} ({err})') from err
    return ViewSettings(urdf, prefix, prefix + root_link(urdf, str(description)))
