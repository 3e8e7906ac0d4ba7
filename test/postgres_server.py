# SPDX-License-Identifier: Apache-2.0
"""A throwaway PostgreSQL server for tests that need a real RDB storage (Optuna studies
shared by several worker processes).

PostgreSQL 15's `initdb` and `pg_ctl` are on PATH on our machines; the server runs in a
temporary directory on a free loopback port with trust authentication, and is stopped and
removed afterwards. PostgreSQL refuses to run as root: under root (CI containers) the
server runs as the `postgres` system user, which owns the data directory.
"""

from __future__ import annotations

import os
import pwd
import shutil
import socket
import subprocess
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

#: Seconds the server may take to start or stop.
START_TIMEOUT = 60.0


def available() -> str:
    """'' if a server can be started here, else why not (for pytest.skip)."""
    for tool in ('initdb', 'pg_ctl'):
        if shutil.which(tool) is None:
            return f'{tool} is not on PATH (PostgreSQL server binaries are needed)'
    if os.geteuid() == 0:
        try:
            pwd.getpwnam('postgres')
        except KeyError:
            return 'running as root and there is no postgres user to run the server'
    return ''


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(('127.0.0.1', 0))
        return int(probe.getsockname()[1])


def _as_server_user(command: list[str]) -> list[str]:
    return ['runuser', '-u', 'postgres', '--', *command] if os.geteuid() == 0 else command


@contextmanager
def postgres_server(database: str = 'lompr') -> Iterator[str]:
    """Start a server, create `database`, yield its SQLAlchemy URL (psycopg 3 driver)."""
    folder = Path(tempfile.mkdtemp(prefix='lompr-pg-'))
    data = folder / 'data'
    if os.geteuid() == 0:
        owner = pwd.getpwnam('postgres')
        os.chown(folder, owner.pw_uid, owner.pw_gid)
    port = _free_port()
    for command in (
            ['initdb', '-D', str(data), '-U', 'postgres', '-A', 'trust', '--no-sync'],
            ['pg_ctl', '-D', str(data), '-l', str(folder / 'server.log'), '-w',
             '-t', str(int(START_TIMEOUT)), '-o',
             f'-p {port} -k {folder} -c listen_addresses=127.0.0.1 -c fsync=off', 'start']):
        subprocess.run(_as_server_user(command), check=True, capture_output=True, text=True,
                       timeout=START_TIMEOUT)
    try:
        url = f'postgresql+psycopg://postgres@127.0.0.1:{port}/{database}'
        _create_database(port, database)
        yield url
    finally:
        subprocess.run(_as_server_user(['pg_ctl', '-D', str(data), '-m', 'immediate', '-w',
                                        'stop']), check=False, capture_output=True,
                       timeout=START_TIMEOUT)
        shutil.rmtree(folder, ignore_errors=True)


def _create_database(port: int, database: str) -> None:
    import psycopg

    deadline = time.monotonic() + START_TIMEOUT
    while True:
        try:
            with psycopg.connect(host='127.0.0.1', port=port, user='postgres',
                                 dbname='postgres', autocommit=True) as connection:
                connection.execute(f'CREATE DATABASE "{database}"')
                return
        except psycopg.OperationalError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)
