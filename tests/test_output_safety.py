"""No command deletes or overwrites what relpoint did not write (the reliability suite, outputs).

Each case runs the real command line in a subprocess where the working directory or signals matter,
and through click's runner elsewhere, and checks the exit code, the one stderr line and that every
user file is byte-for-byte where it was.
"""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from formats.outputs import MARKER
from relpoint_cli.main import cli

REPO = Path(__file__).resolve().parents[1]


def invoke(*args: str) -> tuple[int, str]:
    result = CliRunner().invoke(cli, ["-q", *args])
    return result.exit_code, result.stderr


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def tree(path: Path) -> dict[str, str]:
    """Every file under ``path`` with its SHA-256."""
    return {str(p.relative_to(path)): digest(p) for p in sorted(path.rglob("*")) if p.is_file()}


@pytest.fixture()
def log(tmp_path: Path, small_log: Path) -> Path:
    """A copy of the small log in its own directory (the tests put outputs beside it)."""
    copy = tmp_path / "logs" / "small.mcap"
    copy.parent.mkdir()
    copy.write_bytes(small_log.read_bytes())
    return copy


def run_ekf(log: Path, output: Path | str, *extra: str) -> tuple[int, str]:
    return invoke("run", str(log), "--estimator", "ekf", "-o", str(output), *extra)


def test_a_directory_of_user_files_is_refused_and_kept(tmp_path: Path, log: Path) -> None:
    user = tmp_path / "user"
    (user / "sub").mkdir(parents=True)
    (user / "notes.txt").write_text("mine")
    (user / "sub" / "y.txt").write_text("also mine")
    before = tree(user)
    for extra in ((), ("--overwrite",)):
        code, err = run_ekf(log, user, *extra)
        assert code == 2, err
        assert err.count("\n") == 1 and "is not a relpoint output" in err
        assert tree(user) == before
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".user.")]  # no temporaries left


def test_an_earlier_run_is_replaced_but_not_a_file_added_to_it(tmp_path: Path, log: Path) -> None:
    out = tmp_path / "out"
    assert run_ekf(log, out)[0] == 0
    marker = json.loads((out / MARKER).read_text())
    assert marker["command"] == "run" and "trajectory.tum" in marker["files"]
    first = digest(out / "trajectory.tum")
    code, err = run_ekf(log, out)
    assert code == 0, err
    assert digest(out / "trajectory.tum") == first  # same seed, same output
    (out / "notes.txt").write_text("mine")
    code, err = run_ekf(log, out)
    assert code == 2 and "notes.txt, which relpoint did not write" in err
    assert (out / "notes.txt").read_text() == "mine"


def test_outputs_never_contain_or_are_the_input(tmp_path: Path, log: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    before = digest(log)
    for output in (log.parent, log, tmp_path, Path("/")):
        code, err = run_ekf(log, output)
        assert code == 2, (output, err)
        assert "input" in err or "is a file" in err
    monkeypatch.chdir(log.parent)
    code, err = run_ekf(Path("small.mcap"), ".")
    assert code == 2 and "contains the input" in err
    assert digest(log) == before and sorted(p.name for p in log.parent.iterdir()) == ["small.mcap"]


def test_fuse_cannot_write_over_its_run_or_another_commands_output(tmp_path: Path, log: Path) -> None:
    run_dir = tmp_path / "run"
    assert run_ekf(log, run_dir)[0] == 0
    before = tree(run_dir)
    code, err = invoke("fuse", str(run_dir), "--log", str(log), "-o", str(run_dir))
    assert code == 2 and "is the input" in err
    other = tmp_path / "other"
    assert run_ekf(log, other)[0] == 0
    code, err = invoke("fuse", str(run_dir), "--log", str(log), "-o", str(other))
    assert code == 2 and "holds the output of `relpoint run`" in err and "--overwrite" in err
    code, err = invoke("fuse", str(run_dir), "--log", str(log), "-o", str(other), "--overwrite")
    assert code == 0, err
    assert json.loads((other / MARKER).read_text())["command"] == "fuse"
    assert tree(run_dir) == before


def test_file_outputs_never_overwrite_an_input_or_a_foreign_file(tmp_path: Path, log: Path) -> None:
    run_dir = tmp_path / "run"
    assert run_ekf(log, run_dir)[0] == 0
    tum = run_dir / "trajectory.tum"
    before = digest(tum)
    code, err = invoke("export", str(tum), "-o", str(tum))
    assert code == 2 and "is the input" in err
    code, err = invoke("export", str(tum), "-o", str(tum), "--overwrite")
    assert code == 2 and "is the input" in err
    code, err = invoke("evaluate", str(tum), "--reference", str(log), "--json", str(tum))
    assert code == 2 and "is the input" in err
    assert digest(tum) == before

    mine = tmp_path / "mine.tum"
    mine.write_text("my own notes\n")
    code, err = invoke("export", str(run_dir), "-o", str(mine))
    assert code == 2 and "relpoint did not write it" in err and "--overwrite" in err
    assert mine.read_text() == "my own notes\n"
    assert invoke("export", str(run_dir), "-o", str(mine), "--overwrite")[0] == 0
    assert invoke("export", str(run_dir), "-o", str(mine))[0] == 0  # now relpoint's: replaced freely
    assert mine.read_text().startswith("# relpoint")

    summary = tmp_path / "summary.json"
    summary.write_text('{"mine": true}\n')
    code, err = invoke("evaluate", str(run_dir), "--reference", str(log), "--json", str(summary))
    assert code == 2 and summary.read_text() == '{"mine": true}\n'
    summary.unlink()
    assert invoke("evaluate", str(run_dir), "--reference", str(log), "--json", str(summary))[0] == 0
    assert invoke("evaluate", str(run_dir), "--reference", str(log), "--json", str(summary))[0] == 0


def test_simulate_does_not_overwrite_a_foreign_log(tmp_path: Path, small_log: Path) -> None:
    foreign = tmp_path / "recording.mcap"
    foreign.write_bytes(b"not relpoint's" * 10)
    code, err = invoke("simulate", "-o", str(foreign), "--iterations", "5")
    assert code == 2 and "relpoint did not write it" in err
    assert foreign.read_bytes() == b"not relpoint's" * 10
    ours = tmp_path / "ours.mcap"
    assert invoke("simulate", "-o", str(ours), "--iterations", "5")[0] == 0
    assert invoke("simulate", "-o", str(ours), "--iterations", "6")[0] == 0  # relpoint's own: replaced


def test_symlinks_are_written_through_and_dangling_ones_refused(tmp_path: Path, log: Path) -> None:
    real = tmp_path / "real"
    link = tmp_path / "link"
    link.symlink_to(real, target_is_directory=True)
    real.mkdir()
    assert run_ekf(log, link)[0] == 0
    assert link.is_symlink() and (real / "trajectory.tum").is_file()
    dangling = tmp_path / "dangling"
    dangling.symlink_to(tmp_path / "nowhere")
    code, err = run_ekf(log, dangling)
    assert code == 2 and "dangling symbolic link" in err
    file_link = tmp_path / "t.tum"
    file_link.symlink_to(real / "trajectory.tum")
    assert invoke("export", str(real), "-o", str(tmp_path / "copy.tum"))[0] == 0
    assert invoke("export", str(tmp_path / "copy.tum"), "-o", str(file_link))[0] == 0
    assert file_link.is_symlink()


def test_an_unwritable_place_fails_before_the_run(tmp_path: Path, log: Path) -> None:
    code, err = run_ekf(log, "/proc/relpoint-out")
    assert code == 2 and "cannot write" in err and err.count("\n") == 1


def test_a_closed_stdout_pipe_ends_quietly(small_log: Path) -> None:
    for args in (["info", str(small_log)], ["config", "--estimator", "relpoint"]):
        process = subprocess.Popen([sys.executable, "-m", "relpoint_cli.main", *args], cwd=REPO,
                                   stdout=subprocess.PIPE, stderr=subprocess.PIPE)  # fmt: skip
        assert process.stdout is not None and process.stderr is not None
        process.stdout.read(10)
        process.stdout.close()  # the reader goes away, as `| head -c 10` does
        err = process.stderr.read().decode()
        assert process.wait(timeout=60) == 0, err
        assert "Traceback" not in err and "BrokenPipe" not in err


def test_import_never_writes_over_the_dataset_or_a_foreign_log(tmp_path: Path) -> None:
    import numpy as np
    from PIL import Image

    folder = tmp_path / "seq"
    folder.mkdir()
    for k in range(2):
        Image.fromarray(np.full((16, 20), 1500, dtype=np.uint16)).save(folder / f"frame-{k:06d}.depth.png")
        np.savetxt(folder / f"frame-{k:06d}.pose.txt", np.eye(4))
    dataset = tree(folder)
    inside = folder / "frame-000000.pose.txt"
    code, err = invoke("import", "7scenes", str(folder), "-o", str(inside))
    assert code == 2 and "input" in err
    foreign = tmp_path / "recording.mcap"
    foreign.write_bytes(b"someone else's")
    code, err = invoke("import", "7scenes", str(folder), "-o", str(foreign))
    assert code == 2 and "relpoint did not write it" in err and foreign.read_bytes() == b"someone else's"
    ours = tmp_path / "ours.mcap"
    assert invoke("import", "7scenes", str(folder), "-o", str(ours))[0] == 0
    assert invoke("import", "7scenes", str(folder), "-o", str(ours))[0] == 0  # relpoint's own: replaced
    assert tree(folder) == dataset


def test_temporaries_of_a_killed_writer_are_removed_and_nothing_else(tmp_path: Path) -> None:
    from formats.atomic import remove_temporaries

    (tmp_path / ".job.k3x.partial").mkdir()
    (tmp_path / ".job.k3x.partial" / "trajectory.tum").write_text("0 0 0 0 0 0 0 1\n")
    (tmp_path / ".job.q7.tmp").write_text("half")
    (tmp_path / ".job.z1.old").mkdir()  # a previous output being replaced: kept
    (tmp_path / ".other.k3x.partial").mkdir()  # another target's
    (tmp_path / "job").mkdir()
    assert remove_temporaries(tmp_path / "job") == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == [".job.z1.old", ".other.k3x.partial", "job"]
    assert remove_temporaries(tmp_path / "job") == 0


def test_temporaries_are_found_for_a_name_with_glob_characters(tmp_path: Path) -> None:
    from formats.atomic import remove_temporaries

    (tmp_path / ".sigma=[0.1].k3x.partial").mkdir()
    (tmp_path / ".sigma=0.k3x.partial").mkdir()  # what an unescaped "[0.1]" would match
    assert remove_temporaries(tmp_path / "sigma=[0.1]") == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == [".sigma=0.k3x.partial"]


def test_an_output_set_appears_whole_when_an_interrupt_comes_while_it_is_renamed(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import os
    import signal

    from formats import atomic
    from relpoint.errors import Interrupted

    renamed: list[str] = []

    def replace_and_interrupt(source: object, target: object) -> None:
        if not renamed:
            os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C as the first output is renamed
        real_replace(source, target)
        renamed.append(Path(str(target)).name)

    real_replace = os.replace
    targets = [tmp_path / "a.json", tmp_path / "plots" / "b.png"]
    with pytest.raises(Interrupted, match="interrupted after every output was written"), atomic.output_set():
        for target in targets:
            atomic.write_text(target, "x")
        monkeypatch.setattr(atomic.os, "replace", replace_and_interrupt)
    assert renamed == ["a.json", "b.png"]  # the interrupt waited for the last rename
    assert all(target.read_text() == "x" for target in targets)
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["a.json", "b.png", "plots"]  # no temporary


UNREADABLE_INPUTS = """
import json, sys
from click.testing import CliRunner
from relpoint_cli.main import cli
log, good, run = sys.argv[1:4]
commands = [["info", log], ["run", log, "-e", "ekf", "-o", run + "-x"], ["export", log, "-o", run + ".tum"],
            ["evaluate", log, "-r", good], ["evaluate", run, "-r", log], ["compare", run, "-r", log],
            ["fuse", run, "--log", log, "-o", run + "-fused"]]
print(json.dumps([(c[0], *(lambda r: (r.exit_code, r.stderr))(CliRunner().invoke(cli, c))) for c in commands]))
"""


def test_an_unreadable_log_is_an_input_error_naming_the_way_out(tmp_path: Path, log: Path) -> None:
    import os
    import shutil

    run = tmp_path / "run"
    code, err = invoke("run", str(log), "-e", "ekf", "-o", str(run))
    assert code == 0, err
    locked = tmp_path / "locked.mcap"
    shutil.copy(log, locked)
    locked.chmod(0)
    # root reads any file: drop the capabilities that let it (setpriv, from util-linux)
    prefix = ["setpriv", "--bounding-set", "-dac_override,-dac_read_search"] if os.geteuid() == 0 else []
    if prefix and shutil.which("setpriv") is None:
        pytest.skip("running as root without setpriv: every file is readable")
    probe = subprocess.run([*prefix, "cat", str(locked)], capture_output=True)
    if probe.returncode == 0:
        pytest.skip("this user can read a file of mode 000")
    done = subprocess.run([*prefix, sys.executable, "-c", UNREADABLE_INPUTS, str(locked), str(log), str(run)],
                          capture_output=True, text=True, cwd=REPO, timeout=300)  # fmt: skip
    assert done.returncode == 0, done.stderr
    for command, code, err in json.loads(done.stdout):
        assert code == 3, (command, err)
        assert err == f"relpoint: error: {locked}: cannot read (permission denied); check its permissions\n", command


@pytest.fixture()
def tum_pair(tmp_path: Path, log: Path) -> tuple[Path, Path]:
    """A reference TUM file (the log's ground truth) and a TUM estimate (the same, as relpoint writes both)."""
    reference = tmp_path / "reference.tum"
    assert invoke("export", str(log), "-o", str(reference))[0] == 0
    estimate = tmp_path / "inputs" / "estimate.txt"
    estimate.parent.mkdir()
    estimate.write_bytes(reference.read_bytes())
    return estimate, reference


@pytest.mark.parametrize(
    "args",
    [
        ("export", "{est}", "-o", "e.kitti"),
        ("export", "{est}", "-o", "e.kitti", "--out-times", "times.txt"),
        ("export", "{est}", "-o", "e2.tum", "--format", "kitti"),
        ("export", "{est}", "-o", "e.dat", "--format", "tum"),
        ("export", "{est}", "-o", "e.tum", "--format", "csv"),
        ("evaluate", "{est}", "-r", "{ref}", "--json", "ev.txt"),
        ("evaluate", "{est}", "-r", "{ref}", "--csv", "ev.tsv"),
        ("compare", "{summary}", "-o", "table"),
        ("compare", "{summary}", "-o", "t.md", "--format", "json"),
        ("compare", "{summary}", "-o", "t.md", "--format", "text"),
        ("compare", "{summary}", "-o", "t.txt", "--format", "csv"),
        ("simulate", "-o", "simlog", "--iterations", "5"),
    ],
)
def test_a_rerun_replaces_its_own_output_whatever_its_name(
    tmp_path: Path, tum_pair: tuple[Path, Path], args: tuple[str, ...], monkeypatch: pytest.MonkeyPatch
) -> None:
    estimate, reference = tum_pair
    summary = tmp_path / "inputs" / "summary.json"
    assert invoke("evaluate", str(estimate), "-r", str(reference), "--json", str(summary))[0] == 0
    monkeypatch.chdir(tmp_path)
    command = [arg.format(est=estimate, ref=reference, summary=summary) for arg in args]
    assert invoke(*command) == (0, "")
    code, err = invoke(*command)
    assert code == 0, err


def test_a_comment_that_merely_names_relpoint_does_not_make_a_file_relpoints(
    tmp_path: Path, tum_pair: tuple[Path, Path]
) -> None:
    estimate, _ = tum_pair
    for name, text in (
        ("mine.tum", "# converted from relpoint output by hand\n0.0 0 0 0 0 0 0 1\n"),
        ("notes.txt", "# relpoint is what I used\n"),
        ("other.tum", "# relpoint 1.0\n# my columns\n0.0 0 0 0 0 0 0 1\n"),  # the version line, not the legend
    ):
        mine = tmp_path / name
        mine.write_text(text)
        code, err = invoke("export", str(estimate), "-o", str(mine), "--format", "tum")
        assert code == 2 and "relpoint did not write it" in err
        assert mine.read_text() == text


def test_a_kitti_file_counts_as_relpoints_only_as_written(tmp_path: Path, tum_pair: tuple[Path, Path]) -> None:
    estimate, _ = tum_pair
    kitti, times = tmp_path / "e.kitti", tmp_path / "times.txt"
    assert invoke("export", str(estimate), "-o", str(kitti), "--out-times", str(times))[0] == 0
    copy = tmp_path / "copy.kitti"
    copy.write_bytes(kitti.read_bytes())  # a copy carries no record of who wrote it
    code, err = invoke("export", str(estimate), "-o", str(copy))
    assert code == 2 and "relpoint did not write it" in err
    with times.open("a") as stream:  # an edited file is no longer what relpoint wrote
        stream.write("99.0\n")
    edited = times.read_bytes()
    code, err = invoke("export", str(estimate), "-o", str(kitti), "--out-times", str(times))
    assert code == 2 and "times.txt exists and relpoint did not write it" in err
    assert times.read_bytes() == edited
