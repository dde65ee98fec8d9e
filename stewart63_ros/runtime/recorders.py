"""The recorders running on this machine: how a starting node learns that a
``record`` started before it exists, before DDS discovery shows it.

A node cannot wait for a subscriber it does not know of. A recorder the run
names (``rig --record``) it knows; one started on its own in another
terminal (``record``, then ``rig``) it learns of only when discovery shows it,
and one lost DDS announcement delays that by a participant's re-announcement
period (3 s): meanwhile the node's writers have not matched the recorder, and
what they send is lost to it, unseen (its loss count counts gaps in the
messages of publishers it has matched). ``discovery_settle`` guarded this
with a fixed 4 s in every start.

Instead, ``record`` leaves a note here while it runs (its full node name,
ROS domain, pid), and a starting node waits for each live recorder noted on
its own domain and network namespace as for one it can see: until the
recorder has spoken on /diagnostics and its subscriptions on the node's
topics are matched (``startup.StartupBarrier``). An event, not a clock. A
recorder on another host leaves no note here: name it to the run, or give
the nodes ``discovery_settle`` (docs/running.md).
"""
from __future__ import annotations

import contextlib
import json
import os
import tempfile
from pathlib import Path


def notes_dir() -> Path:
    """Where the notes are: one directory per user, on this machine."""
    base = os.environ.get('XDG_RUNTIME_DIR') or tempfile.gettempdir()
    return Path(base) / ('stewart63-recorders-%d' % os.getuid())


def _netns(pid) -> str:
    try:
        return os.readlink('/proc/%s/ns/net' % pid)
    except OSError:
        return ''


def announce(node_name: str, domain_id: int) -> Path | None:
    """Note that this process records as ``node_name`` (a full node name) on
    ROS domain ``domain_id``; returns the note's path (``withdraw`` it when
    the recording stops), or None if it could not be written (then starting
    nodes rely on discovery alone, as for a recorder on another host)."""
    folder = notes_dir()
    path = folder / ('%d-%d.json' % (int(domain_id), os.getpid()))
    try:
        folder.mkdir(mode=0o700, exist_ok=True)
        tmp = path.with_suffix('.tmp')
        tmp.write_text(json.dumps({'node': node_name, 'domain': int(domain_id),
                                   'pid': os.getpid(), 'netns': _netns('self')}))
        os.replace(tmp, path)
    except OSError:
        return None
    return path


def withdraw(path: Path | None) -> None:
    """Remove a note ``announce`` wrote (a stopping recorder takes nothing new)."""
    if path is not None:
        with contextlib.suppress(OSError):
            path.unlink()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def running(domain_id: int) -> list[str]:
    """The full node names of the recorders noted on ``domain_id`` whose
    process runs, in this network namespace, other than this process. A
    note of a process that died without withdrawing it (SIGKILL) is
    removed."""
    out = []
    me, my_netns = os.getpid(), _netns('self')
    try:
        paths = sorted(notes_dir().glob('%d-*.json' % int(domain_id)))
    except OSError:
        return out
    for path in paths:
        try:
            note = json.loads(path.read_text())
            pid, node = int(note['pid']), str(note['node'])
        except (OSError, ValueError, KeyError, TypeError):
            continue        # being written, or not ours to read
        if pid == me:
            continue        # composed: an in-process recorder is seen at once
        if not _alive(pid):
            withdraw(path)
            continue
        if note.get('netns') != my_netns:
            continue        # another network namespace: another host, for DDS
        out.append(node)
    return out
