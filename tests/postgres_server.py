"""A real PostgreSQL server for the tests: Debian's ``postgresql`` package (installed when
missing and this user is root, as ``scripts/bootstrap.sh`` does for CI), a cluster made by
``initdb`` in a temporary folder, started by ``pg_ctl`` on a free loopback port, one per test
session, with one fresh schema per test. The hosts tests start one on a host of their own
(``address``, ``inside``: the command that runs a program on that host, ``clients``: the
network allowed to connect).

The cluster runs without fsync (a test's data need not survive a crash of the machine) and
wants a password over TCP (scram-sha-256), so that wrong credentials are refused as they are in
production.
"""

from __future__ import annotations

import glob
import itertools
import os
import pwd
import shutil
import socket
import subprocess
import tempfile
from pathlib import Path

import psycopg

__all__ = ["PostgresServer", "find_binaries", "install_postgres", "postgres_problem"]

PORTS = range(18600, 18700)
USER = "cosmos"
PASSWORD = "cosmos-test"


def find_binaries() -> Path | None:
    """The newest ``/usr/lib/postgresql/<version>/bin`` with ``initdb``, or None."""
    found = sorted(
        glob.glob("/usr/lib/postgresql/*/bin/initdb"), key=lambda p: int(Path(p).parts[4])
    )
    return Path(found[-1]).parent if found else None


def install_postgres() -> str | None:
    """Install Debian's ``postgresql`` if missing; None when its binaries are there, else why
    not."""
    if find_binaries() is not None:
        return None
    if os.geteuid() != 0 or shutil.which("apt-get") is None:
        return "PostgreSQL is not installed and this user cannot apt-get install it (not root)"
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    install = ["apt-get", "install", "-y", "-qq", "postgresql"]
    for step in (install, ["apt-get", "update", "-qq"], install):
        subprocess.run(step, env=env, capture_output=True, timeout=900, check=False)
        if find_binaries() is not None:
            return None
    return "apt-get install postgresql failed (see scripts/bootstrap.sh)"


def postgres_problem() -> tuple[Path | None, str | None]:
    """The binaries (installed when missing), or None and why they cannot be had."""
    why = install_postgres()
    binaries = find_binaries()
    if binaries is None:
        return None, why or "no PostgreSQL binaries under /usr/lib/postgresql"
    return binaries, None


def _free_port() -> int:
    for port in PORTS:
        with socket.socket() as probe:
            try:
                probe.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    raise RuntimeError(f"no free port in {PORTS.start}-{PORTS.stop - 1} for PostgreSQL")


class PostgresServer:
    """A cluster of its own, started on construction; :meth:`stop` removes it.

    It listens on ``address`` (loopback: a free port of :data:`PORTS`, else 5432), started
    through ``inside`` (e.g. ``ip netns exec NAME``), and takes password logins over TCP from
    ``clients`` (a CIDR) besides loopback."""

    def __init__(
        self,
        binaries: Path,
        *,
        address: str = "127.0.0.1",
        inside: tuple[str, ...] = (),
        clients: str | None = None,
    ) -> None:
        self.binaries = binaries
        self.address = address
        self.folder = Path(tempfile.mkdtemp(prefix="cosmos-pg-"))
        self.data = self.folder / "data"
        self.port = _free_port() if address == "127.0.0.1" else 5432
        self._names = itertools.count()
        as_root = os.geteuid() == 0
        # initdb and postgres refuse to run as root: the cluster belongs to the postgres user
        self._prefix = ["runuser", "-u", "postgres", "--"] if as_root else []
        password = self.folder / "password"
        password.write_text(PASSWORD + "\n")
        if as_root:
            owner = pwd.getpwnam("postgres")
            os.chown(self.folder, owner.pw_uid, owner.pw_gid)
            os.chown(password, owner.pw_uid, owner.pw_gid)
        self._run(
            "initdb",
            "-D",
            str(self.data),
            "-U",
            USER,
            f"--pwfile={password}",
            "--auth-host=scram-sha-256",
            "--auth-local=trust",
            "--no-sync",
            "-E",
            "UTF8",
            "--locale=C",
        )
        if clients is not None:
            with (self.data / "pg_hba.conf").open("a") as hba:
                hba.write(f"host all all {clients} scram-sha-256\n")
        options = (
            f"-c listen_addresses={address} -p {self.port} -k {self.folder} -c fsync=off "
            "-c synchronous_commit=off -c full_page_writes=off -c max_connections=300"
        )
        self._run(
            "pg_ctl", "-D", str(self.data), "-l", str(self.folder / "log"), "-o", options, "-w",
            "start", inside=inside,
        )  # fmt: skip

    def _run(self, program: str, *args: str, inside: tuple[str, ...] = ()) -> None:
        command = [*inside, *self._prefix, str(self.binaries / program), *args]
        done = subprocess.run(command, capture_output=True, text=True, timeout=120, check=False)
        if done.returncode != 0:
            raise RuntimeError(f"{program} failed: {done.stderr or done.stdout}")

    def url(self, database: str = "postgres", *, password: str = PASSWORD) -> str:
        return f"postgresql://{USER}:{password}@{self.address}:{self.port}/{database}"

    def new_schema(self) -> str:
        """The URL of a fresh, empty schema of the ``postgres`` database (its tables go there:
        it is first on the connections' search path). Made at once, where a database takes
        ~0.7 s to copy from its template; a test that needs a database of its own (to take it
        away) makes one with :meth:`new_database`."""
        name = f"test_{next(self._names)}"
        with psycopg.connect(self.url(), autocommit=True) as admin:
            admin.execute(f'CREATE SCHEMA "{name}"')
        return f"{self.url()}?options=-csearch_path%3D{name}"

    def new_database(self) -> str:
        """The URL of a fresh, empty database."""
        name = f"test_{os.getpid()}_{next(self._names)}"
        with psycopg.connect(self.url(), autocommit=True) as admin:
            admin.execute(f'CREATE DATABASE "{name}"')
        return self.url(name)

    def stop(self) -> None:
        try:
            self._run("pg_ctl", "-D", str(self.data), "-m", "immediate", "stop")
        finally:
            shutil.rmtree(self.folder, ignore_errors=True)
