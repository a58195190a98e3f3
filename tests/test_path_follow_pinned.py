"""Path following gives the same numbers, bit for bit, as before the tick was made cheap (issue 12).

Every figure below was printed by qcarlab before the speed work on the path-following tick (the
reference blocks as plain functions, the scalar look-ahead, the named-tuple Command/Readout/Truth,
the loop's bound appends, the pruned scoring): same seed, same metrics, and the same log (a
SHA-256 of its columns). A change that moves any of them changes what a student is graded on;
if it is meant to (a new simulator model), print the new values with
``python tests/test_path_follow_pinned.py`` and replace the table, saying why in the commit.
"""

from __future__ import annotations

import hashlib
import sys

import numpy as np
import pytest

import qcarlab
from qcarlab import paths
from qcarlab.control.speed import SpeedController
from qcarlab.control.steering import pure_pursuit
from qcarlab.experiments.path_follow import FollowConfig, follow_path

METRICS = ("rms_cross_track_m", "max_cross_track_m", "completion", "final_distance_to_goal_m", "speed_rms_error_mps",
           "mean_speed_mps", "duration_s", "pose_drift_m")


def student_pure_pursuit(pose, target, lookahead, wheelbase):
    """A student's block that is the reference (through StudentBlock: checked and timed)."""
    return pure_pursuit(pose, target, lookahead, wheelbase, max_steering=0.5)


# name: (path, FollowConfig options, blocks, world, seed)
CASES = {
    "circle": (lambda: paths.circle(), {}, None, None, 0),
    "butterfly4": (lambda: paths.butterfly(4, 4), {}, None, None, 0),
    "butterfly2_ld05": (lambda: paths.butterfly(2, 2), {"lookahead": 0.5}, None, None, 0),
    "line_gyro": (lambda: paths.line(3, 4), {"pose": "gyro"}, None, None, 7),
    "circle_truth_turn": (lambda: paths.circle(), {"pose": "truth", "turn_speed": True}, None, None, 0),
    "circle_carrot": (lambda: paths.circle(), {"controller": "carrot"}, None, None, 0),
    "circle_stanley": (lambda: paths.circle(), {"controller": "stanley"}, None, None, 0),
    "circle_laps3": (lambda: paths.circle(), {"laps": 3, "max_time": 30.0}, None, None, 0),  # the benchmark's run
    "circle_student": (lambda: paths.circle(), {},
                       {"pure_pursuit": student_pure_pursuit, "speed_controller": SpeedController}, None, 0),
    "circle_track": (lambda: paths.circle(), {}, None, "track", 0),  # with the world's collision watch
}

# name: ((the METRICS..., ticks), SHA-256 of the log's columns)
PINNED = {
    "circle": ((0.005450142981248079, 0.009612157293841933, 1.0, 0.026486452615650906, 0.05210170201845237, 0.49362316888902397, 18.84, 0.00011533326905583802, 1884),
        "7ed31564e84e261039e5f579b466cd0e95811db06aa12ae085fd0c8f44aab9a2"),
    "butterfly4": ((0.007001695363124794, 0.037952615370803126, 1.0, 0.025845265768441802, 0.025758574133533746, 0.49843172582052386, 75.74000000000001, 0.00026671141428563833, 7574),
        "daf868cb1e91f3890260003f38a28e86b32ede7c11c0308bda8e80805931e9d5"),
    "butterfly2_ld05": ((0.03960116571172851, 0.08837444343986162, 1.0, 0.025102358962066636, 0.03674027730985167, 0.4968112920611112, 37.47, 0.0002452517776666073, 3747),
        "ac4a4cb06f762a0feb9ef096d5c9a2cca49ac105c4eab80e356997bc9c19b6fd"),
    "line_gyro": ((0.0021681951156984802, 0.004566756951481227, 1.0, 0.02524789642354671, 0.09278771059541722, 0.4806418796120615, 6.1899999999999995, 0.004623407637223798, 619),
        "d32609411d38200b40d3fb8afaeaa882d4968afaf4990aaac767134bc618edd8"),
    "circle_truth_turn": ((0.005434971408655628, 0.009526290341951576, 1.0, 0.02670894463489749, 0.04757682499213618, 0.4415716885222743, 21.060000000000002, 0.00011412612289988341, 2106),
        "26a5a3a885b7ec5b8a13d757ce886b7a97201d7b40252f419ab776335865af44"),
    "circle_carrot": ((0.004656921744428001, 0.006351931279058399, 1.0, 0.024764199480106438, 0.052287438778324966, 0.49357862074122694, 18.720000000000002, 0.00012320849454219726, 1872),
        "98367b2f2a7d015fb0fc70b9de45ba3e48ec3223f1bea504a1fe5ab87d52b860"),
    "circle_stanley": ((0.0157033414219984, 0.018051348802025285, 1.0, 0.025644257467361712, 0.05253366459449575, 0.4934965695840765, 18.59, 0.00011089868270023842, 1859),
        "1925ce967cc5eee1e280addba8e84707cffb21424a6619804e6b12813f878df7"),
    "circle_laps3": ((0.005347624185199039, 0.006803943704891102, 0.5310923916408832, 2.8588752535624073, 0.040071045129754033, 0.49965688956238025, 30.0, 0.001796203118938466, 3000),
        "093eeebda290c6712f47542951e4f3b536f018d9361f2e2157c8459232e44da5"),
    "circle_student": ((0.005450142981248079, 0.009612157293841933, 1.0, 0.026486452615650906, 0.05210170201845237, 0.49362316888902397, 18.84, 0.00011533326905583802, 1884),
        "7ed31564e84e261039e5f579b466cd0e95811db06aa12ae085fd0c8f44aab9a2"),
    "circle_track": ((0.16579283244896395, 0.7690260169735214, 1.0, 0.02640520594887607, 0.05454132563951953, 0.49304221991528013, 17.21, 0.0004374343229131586, 1721),
        "2cf8e172a5e6982ad3a6e6721caea94728c18c1ede2efd7d6c73f5454b2286dc"),
}


def run(name):
    make, cfg, blocks, world, seed = CASES[name]
    with qcarlab.open_car("sim", seed=seed, world=world) as car:
        res = follow_path(car, make(), FollowConfig(**cfg), blocks=blocks)
    m = res.metrics
    log = res.logs["log.csv"]
    h = hashlib.sha256()
    for key in sorted(log):
        h.update(key.encode())
        h.update(np.ascontiguousarray(np.asarray(log[key], dtype=float)).tobytes())
    return (*(m[k] for k in METRICS), m["loop"]["ticks"]), h.hexdigest(), m


@pytest.mark.parametrize("name", list(CASES))
def test_same_seed_same_numbers_as_before(name):
    numbers, digest, m = run(name)
    want, want_digest = PINNED[name]
    # the README's and the CLI's digits first (a readable failure), then every bit
    assert [f"{v:.4g}" for v in numbers] == [f"{v:.4g}" for v in want], name
    assert numbers == want, name
    assert digest == want_digest, f"{name}: the log differs from the pinned run"
    if name == "circle_student":  # the student's blocks ran, every tick, through the checks
        assert m["student_blocks"]["speed_controller"]["calls"] == m["loop"]["ticks"]
        assert m["student_blocks"]["pure_pursuit"]["calls"] > 0.9 * m["loop"]["ticks"]


if __name__ == "__main__":  # print the table for a deliberate change of the simulator
    for case in CASES:
        numbers, digest, _ = run(case)
        print(f'    "{case}": (({", ".join(repr(v) for v in numbers)}),\n        "{digest}"),', file=sys.stdout)
