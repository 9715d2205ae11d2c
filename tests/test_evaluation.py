"""Mission sweeps: jobs, reports, the rover eval command, and the Ray executor against the local one."""

import csv
import json
import math

import numpy as np
import pytest

from rover_env.tools.cli import main
from rover_env.tools.evaluation import (
    EvalJob,
    controller_imu,
    jobs_for,
    parse_controller,
    run_sweep,
    summarize,
    write_report,
)


def test_controller_names_and_bad_input():
    spec, source = parse_controller("slip_aware@ground_truth")
    assert spec.action_mode == "wheels" and source == "ground_truth"
    assert parse_controller("slip_unaware")[1] == "estimated"
    with pytest.raises(ValueError, match="unknown"):
        parse_controller("no_such")
    with pytest.raises(ValueError, match="observation source"):
        parse_controller("slip_aware@truth")
    with pytest.raises(ValueError, match="executor"):
        run_sweep([], executor="slurm")
    jobs = jobs_for(["a", "b@ground_truth"], ["m"], [1, 2], out="/o")
    assert [j.name for j in jobs] == ["a_m_1", "a_m_2", "b-ground_truth_m_1", "b-ground_truth_m_2"]
    # policies (and scenario files) of one name in two folders get two run folders
    names = [EvalJob(f"policy:{p}@ground_truth", m, 0).name for p, m in [("/x/run", "/a/s.yaml"),
             ("/y/run", "/a/s.yaml"), ("/x/run", "/b/s.yaml"), ("/x/run", "/a/s.yaml")]]  # fmt: skip
    assert len(set(names)) == 3 and names[0] == names[3] and names[0].startswith("policy-run-")
    assert jobs[2].out == "/o/runs/b-ground_truth_m_1"


def test_an_imu_suffix_drives_on_estimates_with_that_imu():
    assert parse_controller("slip_aware@imu")[1] == "estimated"
    assert controller_imu("slip_aware@imu") == "bmi088"
    assert controller_imu("slip_aware@imu:tactical") == "tactical"
    assert controller_imu("slip_aware") is None and controller_imu("slip_aware@ground_truth") is None
    assert EvalJob("slip_aware@imu:tactical", "Rover-v0", 3).name == "slip_aware-imu-tactical_Rover-v0_3"
    with pytest.raises(ValueError, match="IMU preset 'mems'"):
        parse_controller("slip_aware@imu:mems")


def test_summary_and_report_from_known_rows(tmp_path):
    rows = [
        dict(
            controller="c",
            mission="m",
            seed=s,
            success=ok,
            time=t,
            cross_track_rms=0.1 * s,
            energy=10.0,
            time_in_slip=0.0,
            stuck_events=0,
            progress=5.0,
            est_mae_v_x=0.01,
        )  # fmt: skip
        for s, ok, t in ((0, True, 10.0), (1, False, 30.0), (2, True, 20.0))
    ]
    (s,) = summarize(rows)
    assert s["runs"] == 3 and s["success"] == pytest.approx(2 / 3)
    assert s["time"] == pytest.approx(15.0)  # over the successful runs only
    assert s["cross_track_rms"] == pytest.approx(0.1)
    assert s["est_mae_v_x"] == pytest.approx(0.01) and math.isnan(s["est_slip_f1"])  # no event counts
    counts = [(2, 0, 1), (0, 1, 0), (1, 0, 0)]  # (matched, false, missed) per run
    for r, (tp, fp, fn) in zip(rows, counts, strict=True):
        r |= dict(
            est_slip_events_matched=tp, est_slip_events_false=fp, est_slip_events_missed=fn, est_slip_f1=0.0
        )
    assert summarize(rows)[0]["est_slip_f1"] == pytest.approx(2 * 3 / (2 * 3 + 1 + 1))  # pooled, not 0
    report = write_report(rows, tmp_path).read_text()
    assert "| c | built-in | 3 | 0.667 | 15 | 0.1 | 10 |" in report
    with open(tmp_path / "results.csv") as fh:
        assert len(list(csv.DictReader(fh))) == 3
    assert len(json.loads((tmp_path / "results.json").read_text())) == 3
    # strict JSON: NaN is written as null, and a report made from the file reads it back as NaN
    rows[0]["est_mae_v_x"] = math.nan
    write_report(rows, tmp_path)
    text = (tmp_path / "results.json").read_text()
    assert "NaN" not in text and '"est_mae_v_x": null' in text
    assert summarize(json.loads(text))[0]["est_mae_v_x"] == pytest.approx(0.01)


def test_rover_eval_writes_one_report_of_all_runs(tiny_scenario, tmp_path, capsys):
    out = tmp_path / "eval"
    argv = ["eval", "--controllers", "slip_unaware@ground_truth", "slip_aware@ground_truth"]
    assert (
        main(argv + ["--missions", tiny_scenario, "--seeds", "0-1", "--workers", "1", "--out", str(out)]) == 0
    )
    rows = json.loads((out / "results.json").read_text())
    assert len(rows) == 4 and all(r["success"] for r in rows)
    assert {r["controller"] for r in rows} == {"slip_unaware@ground_truth", "slip_aware@ground_truth"}
    (run,) = (out / "runs").glob("slip_aware-ground_truth_tiny-*_1")  # the scenario file's stem and hash
    assert (run / "trajectory.png").stat().st_size > 1000
    report = (out / "report.md").read_text()
    assert "## " + tiny_scenario in report and "slip_aware@ground_truth | none | 2 | 1 |" in report
    assert "report.md" in capsys.readouterr().out


def _metrics(rows):
    keep = ("controller", "seed", "success", "time", "path_length", "cross_track_rms", "energy")
    return sorted(
        (tuple(r[k] for k in keep), tuple(r[k] for k in sorted(r) if k.startswith("est_"))) for r in rows
    )


@pytest.mark.slow  # starts a Ray cluster: 33 s
def test_ray_executor_gives_the_local_executor_s_metrics(tiny_scenario):
    pytest.importorskip("ray", reason="the ray extra is not installed: pip install 'rover-vision[ray]'")
    jobs = [EvalJob(c, tiny_scenario, s) for c in ("slip_unaware@ground_truth", "slip_aware") for s in (0, 1)]
    local = run_sweep(jobs, executor="local", workers=2)
    ray_rows = run_sweep(jobs, executor="ray")
    assert len(local) == len(ray_rows) == 4
    a, b = _metrics(local), _metrics(ray_rows)
    assert [x[0] for x in a] == [x[0] for x in b]  # identical mission metrics
    for (_, ea), (_, eb) in zip(a, b, strict=True):  # and estimator errors
        np.testing.assert_array_equal(ea, eb)
    assert any(len(e) > 0 for _, e in a)  # the estimated run was scored


def test_slip_detection_scores_are_undefined_without_events_not_zero():
    from rover_env.tools.estimator_metrics import slip_metrics

    t = np.arange(60) / 30.0 + 1.5
    calm = np.zeros((60, 19))
    run = {"t": t, "est": calm, "tru": calm, "events": np.zeros((60, 4), bool), "speed": np.ones((60, 4)),
           "frame": 1 / 30}  # fmt: skip
    m = slip_metrics([run])
    assert m["events"] == 0 and math.isnan(m["f1"]) and math.isnan(m["precision"]) and math.isnan(m["recall"])
    tru = calm.copy()
    tru[10:20, 7] = 0.5  # one true event on FL, missed
    m = slip_metrics([dict(run, tru=tru)])
    assert (m["events"], m["missed"], m["f1"], m["recall"]) == (1, 1, 0.0, 0.0) and math.isnan(m["precision"])


def test_an_estimated_event_on_true_slip_that_peaks_in_the_hysteresis_band_is_no_false_alarm():
    from rover_env.tools.estimator_metrics import slip_metrics

    t = np.arange(90) / 30.0 + 1.5
    tru = np.zeros((90, 19))
    est = tru.copy()
    events = np.zeros((90, 4), bool)
    tru[10:20, 7] = 0.18  # FL peaks in the band [0.15, 0.2): no true event
    events[12:16, 0] = True
    tru[40:50, 8] = 0.12  # FR below the band: an event there is a false alarm
    events[42:46, 1] = True
    tru[60:70, 9] = 0.14  # RL: 0.25 for one frame only is no true event, and no false alarm either
    tru[65, 9] = 0.25
    events[66:68, 2] = True  # called in the two frames after it (the detector confirms over two)
    tru[75, 10] = 0.19  # RR: a one-frame band peak, called two frames after it: still the band's
    events[77:79, 3] = True
    events[85:87, 3] = True  # ... but not eight frames later
    run = {"t": t, "est": est, "tru": tru, "events": events, "speed": np.ones((90, 4)), "frame": 1 / 30}
    m = slip_metrics([run])
    assert (m["events"], m["matched"], m["in_band"], m["false"]) == (0, 0, 3, 2), m
    tru[10:20, 7] = 0.21  # a true event: matched, with no false alarm on that wheel
    m = slip_metrics([dict(run, tru=tru)])
    assert (m["events"], m["matched"], m["in_band"], m["false"]) == (1, 1, 2, 2), m
    assert m["precision"] == 1 / 3
    late = tru.copy()
    late[10:20, 7] = 0.0
    late[9:11, 7] = 0.3  # a true event (frames 9, 10) whose last frame is two before the call (12)
    m = slip_metrics([dict(run, tru=late)])
    assert (m["events"], m["matched"], m["false"]) == (1, 1, 2), m
    assert m["latency_max"] == pytest.approx(3)  # from the truth's first frame at 0.2 (9) to the call (12)
    late[9:11, 7] = 0.0
    late[8:10, 7] = 0.3  # three frames before the call: missed, and the call is a false alarm
    m = slip_metrics([dict(run, tru=late)])
    assert (m["events"], m["matched"], m["false"]) == (1, 0, 3), m


def test_a_sweep_runs_field_cameras_in_a_randomised_world(tiny_scenario, tmp_path):
    """``rover eval --camera-effects field --randomize on``: the rows say so, the seed draws the world
    (two runs of one seed agree), and bad values are refused before anything runs."""
    out = tmp_path / "eval"
    argv = ["eval", "--controllers", "slip_aware", "slip_aware@ground_truth", "--missions", tiny_scenario]
    argv += ["--seeds", "3", "--workers", "1", "--camera-effects", "field", "--randomize", "on"]
    assert main(argv + ["--out", str(out)]) == 0
    rows = {r["controller"]: r for r in json.loads((out / "results.json").read_text())}
    assert rows["slip_aware"]["camera_effects"] == "field" and rows["slip_aware"]["randomize"] == "on"
    assert rows["slip_aware@ground_truth"]["camera_effects"] == "none"
    again = run_sweep([EvalJob("slip_aware@ground_truth", tiny_scenario, 3, randomize="on")], workers=1)
    off = run_sweep([EvalJob("slip_aware@ground_truth", tiny_scenario, 3)], workers=1)
    assert again[0]["energy"] == rows["slip_aware@ground_truth"]["energy"]  # the same world
    assert off[0]["energy"] != again[0]["energy"]  # another world (its friction, its sun)
    with pytest.raises(ValueError, match="randomize"):
        run_sweep([EvalJob("slip_aware", tiny_scenario, 3, randomize="sometimes")], workers=1)
    # without the flag, the scenario's own randomize key holds
    scenario = tmp_path / "randomized.yaml"
    scenario.write_text(open(tiny_scenario).read() + "\nrandomize: on\n")
    (row,) = run_sweep([EvalJob("slip_aware@ground_truth", str(scenario), 3)], workers=1)
    assert row["randomize"] == "on"
    with pytest.raises(SystemExit):
        main(argv[:-2] + ["--out", str(tmp_path / "x"), "--randomize", "maybe"])
    assert not (tmp_path / "x").exists()


def test_resume_takes_a_finished_run_only_for_the_same_cameras_estimator_and_world(tmp_path):
    """A folder started with other cameras (the default was once ``ideal``), another estimator
    or another randomisation is not resumed as if it were this job's; ground-truth runs are."""
    from rover_env.tools.evaluation import finished_row

    def write(row):
        (tmp_path / "row.json").write_text(json.dumps(row))

    base = {"controller": "slip_aware@imu", "mission": "Rover-v0", "seed": 3, "preset": "train"}
    job = EvalJob("slip_aware@imu", "Rover-v0", 3, out=str(tmp_path), randomize="on")
    write({**base, "camera_effects": "field", "estimator": "built-in", "randomize": "on"})
    assert finished_row(job) is not None
    for change in ({"camera_effects": "ideal"}, {"estimator": "mine.py:make"}, {"randomize": "off"}):
        write({**base, "camera_effects": "field", "estimator": "built-in", "randomize": "on", **change})
        assert finished_row(job) is None, change
    # the scenario's own randomisation (None) takes the row's
    write({**base, "camera_effects": "field", "estimator": "built-in", "randomize": "off"})
    assert finished_row(EvalJob("slip_aware@imu", "Rover-v0", 3, out=str(tmp_path))) is not None
    gt = {**base, "controller": "slip_aware@ground_truth", "camera_effects": "none", "estimator": "none"}
    write({**gt, "randomize": "on"})
    assert finished_row(EvalJob("slip_aware@ground_truth", "Rover-v0", 3, out=str(tmp_path), randomize="on"))


def test_a_sweep_names_its_rig_and_resumes_only_the_same_rig(tmp_path):
    from rover_env.tools.evaluation import check_jobs, finished_row

    jobs = jobs_for(["slip_aware@imu"], ["Rover-v0"], [0], rig="fisheye_only")
    assert jobs[0].rig == "fisheye_only"
    with pytest.raises(ValueError, match="rig 'two_fisheyes': use one of"):
        check_jobs(jobs_for(["slip_aware@imu"], ["Rover-v0"], [0], rig="two_fisheyes"))
    row = {"controller": "slip_aware@imu", "mission": "Rover-v0", "seed": 0, "preset": "train"}
    row |= {"camera_effects": "field", "estimator": "built-in", "randomize": "off", "rig": "mission"}
    (tmp_path / "row.json").write_text(json.dumps(row))
    one = EvalJob("slip_aware@imu", "Rover-v0", 0, out=str(tmp_path), rig="fisheye_only")
    assert finished_row(one) is None  # a two-camera run is not the one-camera rig's
    assert finished_row(EvalJob("slip_aware@imu", "Rover-v0", 0, out=str(tmp_path))) is not None
