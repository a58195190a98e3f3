"""``qcarlab grade --ray``: the same task processes on a Ray cluster (a local one, started here)."""

from __future__ import annotations

import os

import pytest

from tests.test_grade_run import SMALL_TASKS, grade_json, small_class

ray = pytest.importorskip("ray", reason="qcarlab[ray] is not installed")


@pytest.fixture(scope="module")
def local_ray():
    os.environ.setdefault("RAY_AUTH_MODE", "disabled")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False)
    yield ray
    ray.shutdown()


def test_ray_gives_the_gradebook_of_a_serial_run(cli, tmp_path, local_ray):
    klass = small_class(tmp_path / "class")
    code, _, err = cli("grade", "stop-sign", "obstacle-avoidance", "--class", klass, *SMALL_TASKS,
                       "--out", tmp_path / "serial")
    assert code == 1, err
    code, _, err = cli("grade", "stop-sign", "obstacle-avoidance", "--class", klass, *SMALL_TASKS,
                       "--ray", "auto", "--out", tmp_path / "ray")
    assert code == 1, err
    assert (tmp_path / "ray" / "gradebook.csv").read_text() == (tmp_path / "serial" / "gradebook.csv").read_text()
    assert grade_json(tmp_path / "ray" / "grade.json") == grade_json(tmp_path / "serial" / "grade.json")


def test_an_unreachable_cluster_is_one_line(cli, monkeypatch):
    monkeypatch.setattr(ray, "is_initialized", lambda: False)

    def refuse(*args, **kwargs):
        raise ConnectionError("Could not find any running Ray instance.")

    monkeypatch.setattr(ray, "init", refuse)
    code, _, err = cli("grade", "stop-sign", "--task", "5.2-task1-block", "--ray", "ray://nowhere:10001")
    assert code == 2 and "--ray ray://nowhere:10001: cannot connect to a Ray cluster" in err
    assert len(err.strip().splitlines()) == 1
