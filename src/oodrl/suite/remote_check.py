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


#: How many of the objects the pipelines to build need `unserved` asks an HTTP remote for, at
#: most, and how many requests at once.
SERVE_SAMPLE = 256
SERVE_REQUESTS = 16


def unserved(root: Path, remote, projects: list[str], timeout: float) -> str | None:
    """Why a read-only HTTP remote will not serve the pipelines to build, in one line: it
    refuses every object they need (HTTP 401, 403) or holds none of them; None where it serves
    one, or names none to ask. DVC's HTTP filesystem reads a refusal as a missing object, so
    `dvc pull --allow-missing` would pull nothing and every stage would run here, in silence.
    The objects are those the projects' committed locks name (the outputs their pending stages
    leave as they were come from there), asked for with HEAD at DVC's layout (files/md5/), a
    few at a time, until one answers 200."""
    import urllib.error
    import urllib.request
    from concurrent.futures import ThreadPoolExecutor

    url = remote.options.get("url", "")
    if url.split("://")[0].lower() not in ("http", "https"):
        return None
    oids = _locked_objects(root, projects)[:SERVE_SAMPLE]
    if not oids:
        return None
    context = ssl_context(remote.options)
    headers = _auth_headers(remote.options)

    def status(oid: str) -> int | str:
        where = f"{url.rstrip('/')}/files/md5/{oid[:2]}/{oid[2:]}"
        request = urllib.request.Request(where, method="HEAD", headers=headers)
        try:
            urllib.request.urlopen(request, timeout=timeout, context=context).close()
        except urllib.error.HTTPError as error:
            return error.code
        except OSError as error:  # URLError, a timeout
            return str(getattr(error, "reason", None) or error)
        return 200

    answers: list[int | str] = []
    with ThreadPoolExecutor(max_workers=SERVE_REQUESTS) as pool:
        for chunk in range(0, len(oids), SERVE_REQUESTS):
            answers += pool.map(status, oids[chunk : chunk + SERVE_REQUESTS])
            if 200 in answers:
                return None
    where = f"DVC remote {remote.name!r} ({url})"
    asked = f"{len(answers)} object{'s' * (len(answers) > 1)}"
    refused = sorted({a for a in answers if a in (401, 403)})
    if len(refused) and all(a in (401, 403) for a in answers):
        return (f"{where} refuses the objects the pipelines to build need (HTTP "
                f"{'/'.join(map(str, refused))} to each of the {asked} asked); check its URL and "
                f"the credentials it wants (docs/how-to/remotes.md)")  # fmt: skip
    kinds = ", ".join(sorted({f"HTTP {a}" if isinstance(a, int) else a for a in answers}))
    return (f"{where} has none of the {asked} the committed locks of "
            f"{', '.join(projects)} name ({kinds}); check that it is the remote their results "
            f"were pushed to (`dvc push` where they were built)")  # fmt: skip


def _locked_objects(root: Path, projects: list[str]) -> list[str]:
    """The md5 of every output the projects' committed dvc.lock files name (a directory's by
    its manifest, `.dir`), each once: a project's locks are the tracked ones whose nearest
    folder holding a .dvc is the project's."""
    import subprocess

    import yaml

    listed = subprocess.run(["git", "ls-files", "-z", "*dvc.lock"], cwd=root, capture_output=True,
                            text=True, check=True).stdout.split("\0")  # fmt: skip
    wanted = {(root / project).resolve() for project in projects}
    oids: dict[str, None] = {}
    for name in filter(None, listed):
        lock = root / name
        owner = next((d for d in lock.parents if (d / ".dvc").is_dir()), None)
        if owner is None or owner.resolve() not in wanted:
            continue
        stages = (yaml.load(lock.read_text(), Loader=yaml.CSafeLoader) or {}).get("stages")
        for stage in (stages or {}).values():
            for out in stage.get("outs", []):
                if out.get("md5"):
                    oids.setdefault(out["md5"])
    return list(oids)


def ssl_context(options):
    """The TLS context DVC's HTTP remote would use: its `ssl_verify` option is a bool or a CA
    bundle."""
    import ssl

    verify = str(options.get("ssl_verify", "true"))
    context = ssl.create_default_context(
        cafile=None if verify.lower() in ("true", "false") else verify
    )
    if verify.lower() == "false":
        context.check_hostname, context.verify_mode = False, ssl.CERT_NONE
    return context


def _auth_headers(options) -> dict[str, str]:
    """The header DVC's HTTP remote sends for its `auth` option (basic, or custom with
    `custom_auth_header`), where the password is configured."""
    import base64

    auth, password = options.get("auth"), options.get("password")
    if auth == "basic" and password is not None:
        token = base64.b64encode(f"{options.get('user', '')}:{password}".encode()).decode()
        return {"Authorization": f"Basic {token}"}
    if auth == "custom" and password is not None and options.get("custom_auth_header"):
        return {options["custom_auth_header"]: password}
    return {}
