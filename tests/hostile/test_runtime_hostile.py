"""Hostile inputs to the verbs that compute (SPEC §22): bad options of the monitor, corrupted
stores and pickles, a params file that is not YAML, and stages interrupted at random points.
Each case: its exit code, one line, no traceback, and no file of the project written or lost
(an interrupted stage leaves its output absent or complete, never half-written)."""

from __future__ import annotations

import random
import shutil
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import pytest
from hostile_cli import OODRL, assert_one_line_error, oodrl, snapshot

from oodrl.io.store import read_trajectories

pytestmark = pytest.mark.slow

DETECTOR = "mahalanobis_distance"


@pytest.fixture(scope="module")
def project(tmp_path_factory, repo_root) -> Path:
    """A pipeline's working directory at CI params: params, the committed policy, the clean
    sets and one fitted detector, made by the stage verbs themselves."""
    root = tmp_path_factory.mktemp("project")
    done = oodrl("check-params", str(repo_root / "ci/params.yaml"), "--merged",
                 str(root / "params.yaml"), cwd=repo_root)  # fmt: skip
    assert done.returncode == 0, done.stderr
    (root / "models").mkdir()
    shutil.copy(repo_root / "models/policy.pt", root / "models/policy.pt")
    for verb, out in (("collect-id", "data/id.zarr"), ("collect-eval", "data/eval.zarr")):
        done = oodrl(verb, "--policy", "models/policy.pt", "--out", out, cwd=root)
        assert done.returncode == 0, done.stderr
    done = oodrl("fit", DETECTOR, "--id", "data/id.zarr", "--out", "models/d.pkl", cwd=root)
    assert done.returncode == 0, done.stderr
    return root


@pytest.fixture
def workdir(project, tmp_path) -> Path:
    """A private copy of the project, so that a case may break its files."""
    copy = tmp_path / "work"
    shutil.copytree(project, copy, ignore=shutil.ignore_patterns("run_meta.yaml"))
    return copy


def _refused(workdir: Path, code: int, args: list[str], *needles: str) -> str:
    before = snapshot(workdir)
    line = assert_one_line_error(oodrl(*args, cwd=workdir), code, *needles)
    after = {k: v for k, v in snapshot(workdir).items() if not k.endswith("run_meta.yaml")}
    assert after == {k: v for k, v in before.items() if not k.endswith("run_meta.yaml")}
    return line


MONITOR = ["monitor", "--env", "CartPole-v1", "--steps", "40"]
MONITOR_CASES = [
    ("post-hoc fault", ["--detector", "cusum", "--fault", "gaussian_state_noise"],
     ["live_gaussian_state_noise"]),
    ("unknown fault", ["--detector", "cusum", "--fault", "nosuch"], ["not a registered fault"]),
    ("negative onset", ["--detector", "cusum", "--fault", "stuck_actuator", "--onset", "-5"],
     ["--onset", "got -5"]),
    ("onset past the episode", ["--detector", "cusum", "--fault", "stuck_actuator", "--onset",
                                "40"], ["--onset", "(40)"]),
    ("unknown detector", ["--detector", "nosuch"], ["neither a registered detector"]),
    ("missing pickle", ["--detector", "absent.pkl"], ["absent.pkl: no such file"]),
    ("a pickle that is not a detector", ["--detector", "pyproject.toml"],
     ["pyproject.toml: not a detector file"]),
    ("alpha 0", ["--detector", "cusum", "--alpha", "0"], ["--alpha must be in (0, 1)"]),
    ("alpha 1", ["--detector", "cusum", "--alpha", "1"], ["--alpha must be in (0, 1)"]),
    ("episodes without a fault", ["--detector", "cusum", "--episodes", "3"], ["--fault"]),
    ("unknown environment", ["--detector", "cusum", "--env", "Nope-v0"], ["Nope-v0"]),
]  # fmt: skip


@pytest.mark.parametrize(
    ("case", "args", "needles"), MONITOR_CASES, ids=[c[0] for c in MONITOR_CASES]
)
def test_monitor_refuses_in_one_line_with_exit_2(case, args, needles, repo_root):
    """From the repository root, where the monitor finds the committed policies; it writes
    nothing there that git would see."""
    status = ["git", "status", "--porcelain", "--", "pipeline", "models", "data"]
    before = subprocess.run(status, cwd=repo_root, capture_output=True, text=True).stdout
    assert_one_line_error(oodrl(*MONITOR, *args, cwd=repo_root), 2, *needles)
    assert subprocess.run(status, cwd=repo_root, capture_output=True, text=True).stdout == before


def _new_files(workdir: Path, before: dict[str, str]) -> set[str]:
    """The files a command added to `workdir` since `before`, its run_meta.yaml aside."""
    return {k for k in snapshot(workdir) if not k.endswith("run_meta.yaml")} - set(before)


def _driven(workdir: Path, driver: str, *args: str) -> subprocess.CompletedProcess:
    """A command run in `workdir` by a Python driver script (below: WRITE_IN_FLIGHT, SIGNAL_IN)."""
    return subprocess.run([sys.executable, "-c", driver, *args], cwd=workdir,
                          capture_output=True, text=True, timeout=120)  # fmt: skip


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def _corrupt_a_chunk(path: Path) -> None:
    """Flip bytes inside one array chunk, keeping the ZIP readable: only the checksum tells."""
    with zipfile.ZipFile(path) as archive:
        entries = {info.filename: archive.read(info) for info in archive.infolist()}
    chunk = max((name for name in entries if "/c/" in name), key=lambda n: len(entries[n]))
    data = bytearray(entries[chunk])
    data[len(data) // 2] ^= 0xFF
    entries[chunk] = bytes(data)
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_STORED) as archive:
        for name, content in entries.items():
            archive.writestr(name, content)


SCORE = ["score", DETECTOR, "--model", "models/d.pkl", "--scores", "scores", "--id",
         "data/id.zarr", "--eval"]  # fmt: skip
CORRUPTIONS = [
    ("truncated store", "data/eval.zarr", _truncate, "unreadable store"),
    ("corrupt chunk", "data/eval.zarr", _corrupt_a_chunk, "array '/states'"),
    ("truncated pickle", "models/d.pkl", _truncate, "not a readable oodrl detector"),
    ("empty pickle", "models/d.pkl", lambda p: p.write_bytes(b""), "not a readable oodrl"),
    ("a store that is a pickle", "data/eval.zarr", lambda p: p.write_bytes(b"\x80\x04N."),
     "unreadable store"),
]  # fmt: skip


@pytest.mark.parametrize(
    ("case", "file", "damage", "what"), CORRUPTIONS, ids=[c[0] for c in CORRUPTIONS]
)
def test_a_corrupted_input_names_it_and_restores_before_rebuilding(
    case, file, damage, what, workdir
):
    damage(workdir / file)
    line = _refused(workdir, 1, [*SCORE, "data/eval.zarr"], file, what)
    assert line.index(f"`dvc checkout --force {file}`") < line.index("dvc repro")
    assert not (workdir / "scores").exists()


PARAMS_CASES = [
    ("not YAML", "env: [unclosed\n", "params.yaml"),
    ("a YAML list", "- 1\n- 2\n", "params.yaml"),
    ("empty", "", "params.yaml"),
]


@pytest.mark.parametrize(("case", "text", "needle"), PARAMS_CASES, ids=[c[0] for c in PARAMS_CASES])
def test_a_params_file_that_is_not_params_is_one_line_and_exit_2(case, text, needle, workdir):
    (workdir / "params.yaml").write_text(text)
    _refused(workdir, 2, ["fit", DETECTOR, "--id", "data/id.zarr", "--out", "x.pkl"], needle)


STAGE_CASES = [
    ("unknown detector", ["fit", "nosuch", "--id", "data/id.zarr", "--out", "x.pkl"], 2, "nosuch"),
    ("unknown injector", ["collect-ood", "nosuch", "--policy", "models/policy.pt", "--eval",
                          "data/eval.zarr", "--out", "x.zarr"], 2, "nosuch"),
    ("score with no set", ["score", DETECTOR, "--model", "models/d.pkl", "--scores", "s"], 2,
     "--eval"),
    ("missing policy", ["collect-eval", "--policy", "absent.pt", "--out", "x.zarr"], 1,
     "absent.pt"),
    ("policy that is not one", ["collect-eval", "--policy", "params.yaml", "--out", "x.zarr"], 1,
     "params.yaml"),
    ("missing ID set", ["fit", DETECTOR, "--id", "absent.zarr", "--out", "x.pkl"], 1,
     "absent.zarr"),
]  # fmt: skip


@pytest.mark.parametrize(
    ("case", "args", "code", "needle"), STAGE_CASES, ids=[c[0] for c in STAGE_CASES]
)
def test_a_stage_verb_refuses_bad_arguments_in_one_line(case, args, code, needle, workdir):
    _refused(workdir, code, args, needle)


SHOW_CASES = [
    ("missing", None, "No report file"),
    ("not YAML", "a: [unclosed\n", "not a YAML report file"),
    ("params, not a report", "seed: 0\n", "neither a results file"),
    ("a broken record", "records: [{detector: a}]\n", "Record 0"),
]


@pytest.mark.parametrize(("case", "text", "needle"), SHOW_CASES, ids=[c[0] for c in SHOW_CASES])
def test_show_refuses_what_is_not_a_report(case, text, needle, workdir):
    if text is not None:
        (workdir / "reports").mkdir()
        (workdir / "reports/r.yaml").write_text(text)
    line = _refused(workdir, 1, ["show", "reports/r.yaml"], needle)
    assert "run `dvc repro` first" not in line


KILLS = [(sig, delay) for sig in (signal.SIGTERM, signal.SIGHUP) for delay in (0.8, 1.6, 2.4, 3.2)]


@pytest.mark.parametrize(("sig", "delay"), KILLS, ids=[f"{s.name}-{d}s" for s, d in KILLS])
def test_an_interrupted_stage_leaves_its_output_absent_or_complete(sig, delay, workdir):
    """collect-eval killed at a point of its run (imports, rollouts, writing): one line, exit
    128 + the signal, and the store is either absent or whole; no temporary file stays."""
    delay += random.Random(f"{sig}{delay}").uniform(0, 0.4)  # a seeded jitter around the point
    before = snapshot(workdir)
    process = subprocess.Popen(
        [OODRL, "collect-eval", "--policy", "models/policy.pt", "--out", "new.zarr"],
        cwd=workdir, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    time.sleep(delay)
    process.send_signal(sig)
    stdout, stderr = process.communicate(timeout=120)
    if process.returncode not in (0, -sig.value):
        # Finished first (0); or signalled before oodrl's handler was installed (imports) or
        # while the interpreter shut down after finishing, when Python's default action applies
        # and nothing can print (-signal). Otherwise oodrl's handler ran: one line.
        done = subprocess.CompletedProcess([], process.returncode, stdout, stderr)
        assert_one_line_error(done, 128 + sig.value, f"interrupted ({sig.name})")
    # SPEC §22: complete or absent. A signal after the store's atomic rename (while run_meta.yaml
    # is written, or on the way out) interrupts a command whose store is already whole.
    if process.returncode == 0 or (workdir / "new.zarr").exists():
        read_trajectories(workdir / "new.zarr", stage=None)
    left = _new_files(workdir, before)
    assert left <= {"new.zarr"}, left


# collect-eval as its console script runs it, with zarr's first file write held: zarr has handed it
# to a worker thread, which sends the signal and writes half a second later, and the process lives
# until it has written, as a slower exit would let it: the write an interrupt leaves in flight,
# made certain instead of left to chance.
WRITE_IN_FLIGHT = """
import atexit, signal, sys, threading, time
import zarr.storage._local as local

original, written = local._put, threading.Event()

def held(*args, **kwargs):
    if getattr(held, "fired", False):
        return original(*args, **kwargs)
    held.fired = True
    # To the main thread, as the kernel delivers a signal from outside; sent to the process from
    # this thread, it could wake nothing until this write returned.
    signal.pthread_kill(threading.main_thread().ident, signal.SIGTERM)
    time.sleep(0.5)  # the main thread unwinds meanwhile
    try:
        return original(*args, **kwargs)
    finally:
        written.set()

local._put = held
atexit.register(written.wait, 5)
sys.argv = ["oodrl", "collect-eval", "--policy", "models/policy.pt", "--out", "new.zarr"]
from oodrl.cli import main
main()
"""


def test_a_signal_during_a_store_write_leaves_no_temporary_folder(workdir):
    """zarr writes on a thread of its own, which an interrupt does not stop: the store's cleanup
    must wait for the write in flight, or the write re-creates the folder the cleanup removed."""
    before = snapshot(workdir)
    done = _driven(workdir, WRITE_IN_FLIGHT)
    assert_one_line_error(done, 128 + signal.SIGTERM, "interrupted (SIGTERM)")
    left = _new_files(workdir, before)
    assert not left, left
    assert not list(workdir.glob(".new.zarr*")), "a temporary folder stayed"


# collect-eval with a signal sent where Python cannot raise it: in a __del__ while the command
# runs (the store is about to be written), and in an exit handler after it has finished.
SIGNAL_IN = """
import atexit, signal, sys, threading, time
import oodrl.io.store

def trip():
    signal.pthread_kill(threading.main_thread().ident, signal.SIGTERM)
    time.sleep(0.05)  # Python runs the handler here, inside the caller that cannot raise

class Tripping:
    def __del__(self):
        trip()

original = oodrl.io.store.write_store

def write_store(*args, **kwargs):
    Tripping()  # dropped at once: its __del__ runs
    time.sleep(1)  # the command's work goes on: the signal must still stop it, before the store
    return original(*args, **kwargs)

# The first redelivery the unraisable hook starts gets a signal while it starts (on a loaded
# machine its own can land there): Python runs the handler inside the hook.
def tripping_start(timer):
    frame = sys._getframe(1)
    while frame is not None and frame.f_code.co_name != "unraisable":
        frame = frame.f_back
    if frame is not None and not tripped:
        tripped.append(timer)
        trip()
    start(timer)

tripped, start = [], threading.Timer.start
if sys.argv[1] in ("del", "hook"):
    oodrl.io.store.write_store = write_store
    if sys.argv[1] == "hook":
        threading.Timer.start = tripping_start
else:
    atexit.register(trip)
sys.argv = ["oodrl", "collect-eval", "--policy", "models/policy.pt", "--out", "new.zarr"]
from oodrl.cli import main
main()
"""


def test_a_signal_where_python_cannot_raise_it_is_not_a_traceback(workdir):
    """In a __del__ Python prints a signal's exception as a traceback and drops it: oodrl keeps
    it quiet and delivers it again, so the command still stops, in one line, with nothing
    half-written. After the command has finished (an exit handler) it is ignored: the output
    is whole, and there is nothing left to unwind."""
    before = snapshot(workdir)
    done = _driven(workdir, SIGNAL_IN, "del")
    assert_one_line_error(done, 128 + signal.SIGTERM, "interrupted (SIGTERM)")
    assert {k for k in snapshot(workdir) if not k.endswith("run_meta.yaml")} == set(before)
    assert not list(workdir.glob("*new.zarr*")), "the store was written after the signal"

    done = _driven(workdir, SIGNAL_IN, "exit")
    assert (done.returncode, done.stderr) == (0, ""), done.stderr
    read_trajectories(workdir / "new.zarr", stage=None)


def test_a_signal_inside_the_hook_that_delivers_one_again_is_not_a_traceback(workdir):
    """A signal can land while the hook above starts the redelivery (its own, on a loaded
    machine, fired before the hook returned): raised there, it too was printed as a traceback
    ("Exception ignored in sys.unraisablehook") and dropped. It is delivered again instead."""
    before = snapshot(workdir)
    done = _driven(workdir, SIGNAL_IN, "hook")
    assert_one_line_error(done, 128 + signal.SIGTERM, "interrupted (SIGTERM)")
    assert {k for k in snapshot(workdir) if not k.endswith("run_meta.yaml")} == set(before)
    assert not list(workdir.glob("*new.zarr*")), "the store was written after the signal"


# collect-eval with a signal that lands while torch initialises: sent, and torch's import held a
# moment, from a finder importlib asks first for torch's C extension.
SIGNAL_IN_TORCH = """
import signal, sys, threading, time
import oodrl.io.store

original = oodrl.io.store.write_store

def write_store(*args, **kwargs):
    # The command's work goes on after torch's import: the signal, delivered once torch is
    # whole, must stop it before the store, however late a loaded machine runs its delivery.
    time.sleep(5)
    return original(*args, **kwargs)

oodrl.io.store.write_store = write_store

class Tripwire:
    fired = False

    def find_spec(self, name, path=None, target=None):
        if name == "torch._C" and not self.fired:
            self.fired = True
            signal.pthread_kill(threading.main_thread().ident, signal.SIGTERM)
            time.sleep(0.3)  # the handler runs in here, inside torch's import
            print("torch's import went on", file=sys.stderr)
        return None

sys.meta_path.insert(0, Tripwire())
sys.argv = ["oodrl", "collect-eval", "--policy", "models/policy.pt", "--out", "new.zarr"]
from oodrl.cli import main
main()
"""


def test_a_signal_while_torch_initialises_waits_for_it(workdir):
    """Raised inside torch's initialisation, an interrupt could abort the process (exit 134,
    a C++ backtrace); it is delivered once torch is imported, and the command stops as any
    other interrupted command: one line, nothing written."""
    before = snapshot(workdir)
    done = _driven(workdir, SIGNAL_IN_TORCH)
    assert_one_line_error(done, 128 + signal.SIGTERM, "interrupted (SIGTERM)")
    assert "torch's import went on" in done.stderr, done.stderr
    assert {k for k in snapshot(workdir) if not k.endswith("run_meta.yaml")} == set(before)


# collect-eval with an interrupt that code it calls catches and drops, as C code that calls back
# into Python can (an extension module's initialisation that imports a module); the command's
# work then goes on for seconds before its store.
SIGNAL_DROPPED = """
import signal, sys, threading, time
import oodrl.io.store

original = oodrl.io.store.write_store

def write_store(*args, **kwargs):
    try:
        signal.pthread_kill(threading.main_thread().ident, signal.SIGTERM)
        time.sleep(0.3)  # the handler raises in here
    except KeyboardInterrupt:
        print("the interrupt was dropped", file=sys.stderr)
    time.sleep(5)
    return original(*args, **kwargs)

oodrl.io.store.write_store = write_store
sys.argv = ["oodrl", "collect-eval", "--policy", "models/policy.pt", "--out", "new.zarr"]
from oodrl.cli import main
main()
"""


def test_an_interrupt_a_library_drops_is_raised_again(workdir):
    """A command still running a moment after its interrupt was raised gets it again: it stops
    in one line, before its store, instead of running to its end and exiting by the signal."""
    before = snapshot(workdir)
    done = _driven(workdir, SIGNAL_DROPPED)
    assert "the interrupt was dropped" in done.stderr, done.stderr
    assert_one_line_error(done, 128 + signal.SIGTERM, "interrupted (SIGTERM)")
    assert {k for k in snapshot(workdir) if not k.endswith("run_meta.yaml")} == set(before)


# collect-eval with a signal that lands while the store's temporary folder is removed, after the
# store was renamed into place: sent from the folder's first os.rmdir once new.zarr exists.
SIGNAL_IN_REMOVAL = """
import os, signal, sys, threading, time

original = os.rmdir

def rmdir(*args, **kwargs):
    if os.path.exists("new.zarr") and not getattr(rmdir, "fired", False):
        rmdir.fired = True
        signal.pthread_kill(threading.main_thread().ident, signal.SIGTERM)
        time.sleep(0.05)  # the handler runs in here, inside shutil.rmtree
    return original(*args, **kwargs)

os.rmdir = rmdir
sys.argv = ["oodrl", "collect-eval", "--policy", "models/policy.pt", "--out", "new.zarr"]
from oodrl.cli import main
main()
"""


def test_a_signal_while_a_temporary_folder_is_removed_waits_for_it(workdir):
    """Raised inside shutil.rmtree, an interrupt would leave the temporary folder half removed;
    it is delivered once the removal is done: one line, the store whole, no temporary left."""
    before = snapshot(workdir)
    done = _driven(workdir, SIGNAL_IN_REMOVAL)
    assert_one_line_error(done, 128 + signal.SIGTERM, "interrupted (SIGTERM)")
    assert _new_files(workdir, before) == {"new.zarr"}
    assert not list(workdir.glob(".new.zarr*")), "a temporary folder stayed"
    read_trajectories(workdir / "new.zarr", stage=None)


def test_show_warns_when_the_results_inputs_changed(tmp_path):
    """`oodrl show` on a DVC output whose inputs changed since it was computed says so (a real
    git + DVC repository laid out as an oodrl project: a params edit reaches the results stage
    through `check_params` only); on a current output, on one whose inputs are absent as in a
    clone that pulled nothing, and on a file DVC does not output, it is silent."""

    def git_dvc(*args: str) -> None:
        subprocess.run(args, cwd=tmp_path, check=True, capture_output=True)

    git_dvc("git", "init", "-q")
    git_dvc(str(Path(OODRL).with_name("dvc")), "init", "-q")
    (tmp_path / "params.yaml").write_text("seed: 0\n")
    (tmp_path / "in.yaml").write_text("sweep: {}\n")
    (tmp_path / "dvc.yaml").write_text(
        "stages:\n"
        "  check_params:\n    cmd: cp params.yaml checked\n"
        "    deps: [params.yaml]\n    outs: [checked]\n"
        "  mid:\n    cmd: cp in.yaml mid.yaml\n    deps: [checked, in.yaml]\n    outs: [mid.yaml]\n"
        "  copy:\n    cmd: mkdir -p reports && cp mid.yaml reports/results.yaml\n"
        "    deps: [checked, mid.yaml]\n    outs: [reports/results.yaml]\n"
    )
    git_dvc(str(Path(OODRL).with_name("dvc")), "repro", "-q")
    current = oodrl("show", "reports/results.yaml", cwd=tmp_path)
    assert current.returncode == 0 and current.stderr == ""
    assert oodrl("show", "in.yaml", cwd=tmp_path).stderr == ""
    for unpulled in ("checked", "mid.yaml"):  # a clone that pulled nothing: nothing changed
        (tmp_path / unpulled).unlink()
    assert oodrl("show", "reports/results.yaml", cwd=tmp_path).stderr == ""
    (tmp_path / "params.yaml").write_text("seed: 1\n")  # two stages upstream of the results
    stale = oodrl("show", "reports/results.yaml", cwd=tmp_path)
    assert stale.returncode == 0 and stale.stderr.count("\n") == 1
    assert stale.stderr.startswith("warning: reports/results.yaml may be stale")
