"""A saved ``qcarlab ping --out DIR`` run (sheet 3.1) records its command, so ``grade --results`` grades it."""

from __future__ import annotations

import csv
import json

import pytest

from qcarlab.net.server import CarServer
from qcarlab.net.testing import SyntheticCar

TOKEN = "the-class-token-0123456789"


@pytest.fixture
def served():
    srv = CarServer(SyntheticCar(), "127.0.0.1", 0, token=TOKEN).start()
    yield srv
    srv.stop()


def test_a_saved_ping_run_grades_and_keeps_no_token(cli, served, tmp_path):
    runs = tmp_path / "runs"
    code, out, err = cli("ping", served.uri, "--count", "20", "--interval", "0.05", "--token", TOKEN,
                         "--out", runs / "3.1-ping")
    assert code == 0, err
    saved = (runs / "3.1-ping" / "results.json").read_text()
    assert TOKEN not in saved
    res = json.loads(saved)
    assert res["invocation"]["command"] == "ping" and res["invocation"]["params"]["token"] == "(given)"
    assert res["received"] == 20
    with open(runs / "3.1-ping" / "rtt.csv") as f:
        rows = list(csv.DictReader(f))
    assert [int(r["reply"]) for r in rows] == list(range(1, 21)) and all(float(r["rtt_ms"]) > 0 for r in rows)
    code, out, err = cli("grade", "connectivity", "--results", runs, "--json")
    task = json.loads(out)["tasks"][0]
    assert task["problem"] is None, task  # the saved run is the task's own (its round-trip bounds depend on the load)
    verdicts = {c["criterion"]: c["passed"] for c in task["criteria"]}
    assert verdicts["reachable >= 1"] and verdicts["loss <= 0"], task
    # a run with other options than the task's is still refused, naming the option
    code, _, err = cli("ping", served.uri, "--count", "3", "--interval", "0.05", "--token", TOKEN,
                       "--out", runs / "3.1-ping")
    assert code == 0, err
    code, out, _ = cli("grade", "connectivity", "--results", runs, "--json")
    task = json.loads(out)["tasks"][0]
    assert code == 1 and task["problem"] == "the results were made with --count 3, the task's command has 20"


def test_an_unreachable_car_is_saved_as_unreachable(cli, tmp_path):
    import socket

    probe = socket.create_server(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    code, _, err = cli("ping", f"tcp://127.0.0.1:{port}", "--count", "20", "--interval", "0.05",
                       "--out", tmp_path / "3.1-ping")
    assert code == 1 and "refused" in err
    res = json.loads((tmp_path / "3.1-ping" / "results.json").read_text())
    assert res["reachable"] is False and res["invocation"]["command"] == "ping"
    code, out, _ = cli("grade", "connectivity", "--results", tmp_path, "--json")
    task = json.loads(out)["tasks"][0]
    assert code == 1 and task["criteria"][0]["reason"] == "reachable = 0, below the minimum 1"
