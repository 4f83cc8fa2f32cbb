"""A throw-away PostgreSQL server for the tests: Debian's `postgresql` package (SYSTEM_PKGS in
the Makefile), initdb'd in a temporary directory, run as the unprivileged `postgres` user
when the tests run as root (PostgreSQL refuses to run as root), on a free loopback port,
stopped and removed after. If it cannot start, the fixture fails with the reason: the
PostgreSQL tests never skip."""
from __future__ import annotations

import glob
import os
import pwd
import shutil
import socket
import subprocess
import tempfile
import time
from pathlib import Path


def pg_bindir() -> Path:
    """The newest /usr/lib/postgresql/<major>/bin with initdb and pg_ctl (Debian's layout; not
    whatever pg_ctl happens to be first on PATH)."""
    cands = [Path(p) for p in glob.glob("/usr/lib/postgresql/*/bin")
             if (Path(p) / "initdb").is_file() and (Path(p) / "pg_ctl").is_file()]
    if not cands:
        raise RuntimeError("PostgreSQL server binaries not found under /usr/lib/postgresql/*/bin: "
                           "install Debian's postgresql package (`make test` does: SYSTEM_PKGS)")
    return max(cands, key=lambda p: int(p.parent.name) if p.parent.name.isdigit() else 0)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class PgServer:
    def __init__(self):
        self.bindir = pg_bindir()
        self.as_root = os.geteuid() == 0
        self.user = "postgres" if self.as_root else pwd.getpwuid(os.geteuid()).pw_name
        self.base = Path(tempfile.mkdtemp(prefix="imubench-pg-"))
        self.data = self.base / "data"
        self.port = _free_port()
        self.log = self.base / "server.log"
        if self.as_root:
            pw = pwd.getpwnam("postgres")
            os.chown(self.base, pw.pw_uid, pw.pw_gid)
        self.started = False

    def _run(self, *args, check=True, timeout=120):
        kw = {"user": "postgres", "group": "postgres", "extra_groups": []} if self.as_root else {}
        r = subprocess.run([str(a) for a in args], capture_output=True, text=True, timeout=timeout,
                           cwd=self.base, **kw)
        if check and r.returncode != 0:
            raise RuntimeError(f"{Path(str(args[0])).name} failed (exit {r.returncode}):\n{r.stdout}\n{r.stderr}"
                               + self.log_tail())
        return r

    def log_tail(self) -> str:
        try:
            return "\n--- server log:\n" + "\n".join(self.log.read_text().splitlines()[-20:])
        except OSError:
            return ""

    def start(self) -> "PgServer":
        self._run(self.bindir / "initdb", "-D", self.data, "-U", "imubench", "--auth=trust", "-E", "UTF8",
                  "--no-locale", "--no-sync")
        opts = (f"-p {self.port} -c listen_addresses=127.0.0.1 -c unix_socket_directories={self.base} "
                "-c fsync=off -c max_connections=50")
        self._run(self.bindir / "pg_ctl", "-D", self.data, "-l", self.log, "-o", opts, "-w", "-t", "60", "start")
        self.started = True
        deadline = time.monotonic() + 30
        while True:
            r = self._run(self.bindir / "pg_isready", "-h", "127.0.0.1", "-p", self.port, check=False)
            if r.returncode == 0:
                break
            if time.monotonic() > deadline:
                raise RuntimeError("PostgreSQL did not accept connections within 30 s" + self.log_tail())
            time.sleep(0.2)
        return self

    def createdb(self, name: str) -> str:
        """A new empty database; returns its postgresql:// URL."""
        self._run(self.bindir / "createdb", "-h", "127.0.0.1", "-p", self.port, "-U", "imubench", name)
        return self.url(name)

    def url(self, name: str) -> str:
        return f"postgresql://imubench@127.0.0.1:{self.port}/{name}"

    def stop(self) -> None:
        try:
            if self.started:
                self._run(self.bindir / "pg_ctl", "-D", self.data, "-m", "fast", "-w", "-t", "60", "stop",
                          check=False)
        finally:
            shutil.rmtree(self.base, ignore_errors=True)
