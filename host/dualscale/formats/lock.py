"""The lock of an output folder that one process writes (``RUN/.dualscale-lock``): its one
writer and reader.  The file holds the holder's PID, start time and command (JSON), for the
message a second process gets; the lock itself is the OS's (``fcntl.flock``)."""

from __future__ import annotations

import os
from datetime import datetime
from pathlib import Path

from dualscale.errors import InputError

#: the lock file of a folder a command is writing (:class:`FolderLock`)
LOCK_FILE = ".dualscale-lock"


class FolderLock:
    """An exclusive lock on a run folder (or any output folder) that one process writes: an OS
    lock (``fcntl.flock``) on ``FOLDER/.dualscale-lock``, which holds the holder's PID, start
    time and command (JSON) for the message a second process gets.

    The kernel releases the lock when its process ends, however it ends (``kill -9`` included),
    so a lock file left behind never blocks: only a live holder does.  :meth:`release` removes
    the file.  Two commands on one run folder would both write ``RUN/work/<stage>/`` (issue 24
    §7); the second is refused instead: :meth:`acquire` raises
    :class:`~dualscale.errors.InputError` (exit 2, like any output folder the command cannot
    use) "``FOLDER`` is in use by PID ... (started ...)".  On a filesystem without locks
    (``ENOLCK``, ``EOPNOTSUPP``) the folder is used unlocked, as before.  Use it as a context
    manager; the folder must exist."""

    def __init__(self, folder: str | Path, command: str) -> None:
        self.folder, self.command = Path(folder), command
        self.path = self.folder / LOCK_FILE
        self._fd: int | None = None

    def acquire(self) -> "FolderLock":
        import errno
        import fcntl
        import json

        for _ in range(100):  # retried only while another process removes the file under us
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o666)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as e:
                os.close(fd)
                if e.errno in (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS):
                    return self  # no locks on this filesystem: unlocked, as before
                if e.errno not in (errno.EAGAIN, errno.EWOULDBLOCK, errno.EACCES):
                    raise
                raise InputError(self._in_use()) from None
            try:  # the file we locked must still be the one at the path (a holder removes it on release)
                same = os.fstat(fd).st_ino == os.stat(self.path).st_ino
            except FileNotFoundError:
                same = False
            if not same:
                os.close(fd)
                continue
            info = {"pid": os.getpid(), "started": datetime.now().astimezone().isoformat(timespec="seconds"),
                    "command": self.command}
            os.ftruncate(fd, 0)
            os.write(fd, (json.dumps(info) + "\n").encode())
            self._fd = fd
            return self
        raise InputError(self._in_use())

    def _in_use(self) -> str:
        import json

        try:
            info = json.loads(self.path.read_text())
            who = f"PID {int(info['pid'])} (started {info.get('started')}, `dualscale {info.get('command')}`)"
        except (OSError, ValueError, TypeError, KeyError):
            who = "another process (starting)"
        return (f"{self.folder} is in use by {who}: two commands writing one folder would spoil each other's "
                "work; wait for that one to end (then run this command again to resume), or choose another folder")

    def release(self) -> None:
        """Remove the lock file and release the lock (nothing when not held)."""
        if self._fd is None:
            return
        fd, self._fd = self._fd, None
        try:
            if os.stat(self.path).st_ino == os.fstat(fd).st_ino:
                self.path.unlink()
        except OSError:
            pass
        os.close(fd)  # closing the last descriptor releases the flock

    def __enter__(self) -> "FolderLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()
