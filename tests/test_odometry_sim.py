"""The odometry paper's shadow ablation in the simulator, on a short stretch of the 5 m arc."""

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import odometry_shadow_ablation as ablation  # noqa: E402


@pytest.mark.slow
def test_mask_and_ransac_track_the_arc_where_no_robustness_fails(tmp_path):
    camera, frames, poses, planes, shadow = ablation.record(1.5, "full", 30.0, 225.0)
    truth, results = ablation.evaluate(camera, frames, poses, planes)
    a = results["(a) no robustness"]
    c = results["(c) mask + RANSAC + validity gate"]
    print(
        {
            k: (round(v["speed_rms"], 4), round(v["zero_share"], 3), round(v["locked_share"], 2))
            for k, v in results.items()
        }
    )
    assert shadow > 0.15  # the rover's shadow is in view
    assert a["end_error_share"] > 0.2 and a["bad_share"] > 0.5  # fails
    assert c["valid_share"] == 1.0 and c["zero_share"] == 0.0
    assert c["speed_rms"] <= 0.02 * 2.0 and c["yaw_rate_rms"] <= 0.02
    assert c["end_error_share"] <= 0.01
    assert c["locked_share"] < 0.05 < results["(b) RANSAC only"]["locked_share"]  # the mask's doing
    assert ablation.plot(tmp_path, poses[1:, 0], truth, poses, results).stat().st_size > 10_000
