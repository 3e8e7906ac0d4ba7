"""A private DDS domain for a test session or a bench: nodes there hear nothing else.

ROS 2 documents domain IDs 0-101 as safe on every platform (higher ones can collide with
the ephemeral port range on Linux). Two processes on one machine that picked the same ID
would hear each other's topics, so an ID is reserved with an exclusive lock on a file in
the temporary directory, held until the process ends; the next free ID is taken otherwise.
Call `isolate_ros_domain()` before rclpy creates a context (it reads the environment then).
"""

from __future__ import annotations

import fcntl
import os
import tempfile
from pathlib import Path
from typing import IO

#: The portable range of ROS_DOMAIN_ID, inclusive.
SAFE_DOMAIN_IDS = range(1, 102)

_held: list[IO[bytes]] = []  # the lock files, open for the life of the process


def reserve_domain_id() -> int:
    """A domain ID in `SAFE_DOMAIN_IDS` that no other process of this machine holds."""
    first = os.getpid() % len(SAFE_DOMAIN_IDS)
    ids = list(SAFE_DOMAIN_IDS)
    for domain in ids[first:] + ids[:first]:
        lock = Path(tempfile.gettempdir()) / f'lompr_ros_domain_{domain}.lock'
        stream = open(lock, 'wb')  # noqa: SIM115 - held open (locked) until the process ends
        try:
            fcntl.flock(stream, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            stream.close()
            continue
        _held.append(stream)
        return domain
    msg = f'every ROS domain ID in {SAFE_DOMAIN_IDS.start}-{SAFE_DOMAIN_IDS.stop - 1} is taken'
    raise RuntimeError(msg)


def isolate_ros_domain() -> int:
    """Set ROS_DOMAIN_ID to a reserved ID and discovery to this host only; returns the ID.
    Child processes inherit both through the environment."""
    domain = reserve_domain_id()
    os.environ['ROS_DOMAIN_ID'] = str(domain)
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    return domain
