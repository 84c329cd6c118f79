"""The pool a job runs on: the local pool by default, without Ray; bad `--ray` options refused."""

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from sim_harness.cli import main
from sim_harness.sim.executor import LocalPool


def _square(x: int) -> int:
    return x * x


def test_a_normal_run_never_imports_ray(tmp_path: Path) -> None:
    out = tmp_path / "tiny"
    script = textwrap.dedent(
        f"""
        import sys
        from sim_harness.cli import main
        code = main(["dataset", "generate", "--preset", "smoke", "--train", "10", "--val", "10",
                     "--test", "10", "--max-run-s", "0.3", "--workers", "1", "--no-progress",
                     "--out", {str(out)!r}])
        assert code == 0, code
        import sim_harness.experiments.runner, sim_harness.experiments.aggregate
        print("ray" in sys.modules, "sim_harness.sim.ray_pool" in sys.modules)
        """
    )
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=240, check=True
    )
    assert done.stdout.split()[-2:] == ["False", "False"], done.stdout + done.stderr
    assert (out / "manifest.json").exists()


def test_the_one_worker_pool_runs_tasks_in_this_process_one_at_a_time() -> None:
    pool = LocalPool(1)
    assert (pool.info.slots, pool.same_files) == (1, True)
    task = pool.submit(_square, 7)
    assert pool.wait([task]) == [task] and task.result() == 49
    failing = pool.submit(_square, "x")  # the task's own error, raised where its result is taken
    with pytest.raises(TypeError):
        failing.result()
    pool.close()


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["dataset", "generate", "--ray-shared-dir", "/x"], "--ray-shared-dir needs --ray"),
        (["dataset", "generate", "--ray", "auto", "--workers", "2"], "--workers sets the local"),
        (["dataset", "aggregate", "--out", "o", "--ray", "auto", "--workers", "2"], "--workers"),
        (["experiments", "--ray", "auto", "--workers", "2"], "--workers sets the local pool"),
    ],
)
def test_cluster_options_that_contradict_are_refused_in_one_line(
    argv: list[str], message: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "m.pt").write_bytes(b"")
    if argv[0] == "experiments":
        argv = [*argv, "--model", "m.pt"]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("swarm-sim: error: ") and message in err and "\n" not in err


def test_without_the_cluster_extra_ray_names_the_install_command(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)  # what `import ray` does where it is missing
    argv = ["dataset", "generate", "--preset", "smoke", "--ray", "local", "--no-progress"]
    assert main([*argv, "--out", str(tmp_path / "d")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == "swarm-sim: error: --ray needs Ray: pip install -e '.[cluster]'"
