"""A DVC remote at fault, named (SPEC §22): which object, at which remote, and how it failed.

DVC trusts what an HTTP remote serves unless the remote's `verify` option is on: a corrupt or
truncated object then lands in the cache and is checked out as the output (and `dvc pull` exits
0). `oodrl suite run` turns `verify` on in the DVC config it gives every project
(`oodrl.suite.run._dvc_config`), so DVC hashes each object it fetches and drops one whose hash
is not its name: the cache holds only objects whose hash matches. But DVC then says nothing
(`dvc pull --allow-missing` exits 0, as for an object the remote lacks) or only "unexpected
error" or "failed to transfer '<hash>'". So after each pull, and after any DVC command that
fails, the run asks: which of the project's cached outputs (by their dvc.lock hashes, a
directory's files by its manifest) are still missing from the cache although the remote has
them? The first is fetched once more, into memory, and its failure named: the connection
broke mid-object, the object came short of the size the lock records, or its bytes hash to
something else. Nothing of it is written anywhere.

The check runs as a process (`CHECK`) in the project's directory with the DVC config the
commands had, on the node that ran them (a Ray task's too).
"""

from __future__ import annotations

import json
from pathlib import Path

#: Prints, as JSON, the objects of the project in the working directory that the cache lacks
#: and the remote has (path, hash, size), how many, and the first one's failure when fetched
#: again; `{}` when none.
CHECK = r"""
import hashlib, json, os, sys
from dvc.repo import Repo
from dvc_data.hashfile.tree import Tree

with Repo(".") as repo:
    cache = repo.cache.local
    needed = {}
    for stage in repo.index.stages:
        for out in stage.outs:
            info = out.hash_info
            if not out.use_cache or not info or not info.value or info.name != "md5":
                continue
            path = os.path.relpath(out.fs_path, repo.root_dir)
            needed.setdefault(info.value, (path, out.meta.size if out.meta else None))
            if info.isdir and cache.exists(info.value):
                for key, meta, entry in Tree.load(cache, info):
                    size = meta.size if meta else None
                    needed.setdefault(entry.value, (os.path.join(path, *key), size))
    missing = [oid for oid in needed if not cache.exists(oid)]
    if not missing:
        print("{}")
        sys.exit(0)
    remote = repo.cloud.get_remote_odb(None, "pull")
    existing = set(remote.oids_exist(missing))
    held = [oid for oid in missing if oid in existing]
    found = {}
    for oid in held:
        path, size = needed[oid]
        where = remote.oid_to_path(oid)
        try:
            data = remote.fs.cat_file(where)
        except Exception as error:
            why = " ".join(str(error).split()) or type(error).__name__
            failure = f"the connection broke mid-object ({type(error).__name__}: {why})"
        else:
            actual = hashlib.md5(data).hexdigest()
            if actual == oid.split(".")[0]:
                continue  # whole this time: a passing fault, which the next fetch gets past
            if size is not None and len(data) < size:
                failure = f"truncated: {len(data)} of its {size} bytes arrived"
            else:
                failure = f"corrupt: {len(data)} bytes that hash to {actual}"
        found = {"path": path, "oid": oid, "url": where, "failure": failure}
        break
    if found:
        found["count"] = len(held)
    print(json.dumps(found))
"""


def bad_object(project: Path, environment: dict[str, str], remote, spawn) -> str | None:
    """The one line naming the first object of `project` that the remote failed to deliver
    intact, or None when every object the remote has reached the cache whole (or the check
    itself cannot run: the caller's own error stands). `spawn(command, cwd, environment)` runs
    the check with the environment the DVC commands had (`oodrl.suite.run._spawn`)."""
    import sys

    done = spawn([sys.executable, "-c", CHECK], project, environment)
    if done.returncode != 0:
        return None
    try:
        found = json.loads(done.stdout.strip().splitlines()[-1])
    except (ValueError, IndexError):
        return None
    if not found:
        return None
    more = found["count"] - 1
    others = f" ({more} more object{'s' * (more > 1)} of this project failed too)" if more else ""
    return (
        f"DVC remote {remote.name!r} ({remote.options.get('url')}) did not deliver "
        f"{found['path']} intact (object {found['oid']}, {found['url']}): {found['failure']}"
        f"{others}; nothing of it was kept (DVC verifies each object it fetches: the cache "
        f"holds only objects whose hash matches their name); repair or re-push that object at "
        f"the remote, then run again"
    )
