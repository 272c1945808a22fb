"""The demo's report.md shows the fit with its robust interval (thinshell_ros.demo.write_run_report)."""

from __future__ import annotations

from thinshell_ros.demo import DemoResult, write_run_report


def test_report_shows_the_robust_two_sigma_interval_its_method_and_the_replay_dt(tmp_path):
    fit = {"params": {"gel.youngs_modulus": 2.8e5}, "initial": {"gel.youngs_modulus": 3.0e5},
           "sigma": {"gel.youngs_modulus": 1.0e2}, "sigma_robust": {"gel.youngs_modulus": 5.0e3},
           "robust_method": "hac", "dt": 0.01}
    result = DemoResult(run_dir=tmp_path, recorded_bag=tmp_path / "bag", fit=fit)
    text = write_run_report(tmp_path, result, {"gel.youngs_modulus": 2.9e5}).read_text()
    assert "| gel.youngs_modulus | 3e+05 | 2.8e+05 | 1e+02 | [2.7e+05, 2.9e+05] | 290000.0 |" in text
    assert "Replayed at dt = 0.01 s" in text and "(hac, sysid.covariance)" in text


def test_report_of_a_fit_without_robust_sigma_says_so(tmp_path):
    fit = {"params": {"gel.youngs_modulus": 2.8e5}, "initial": {"gel.youngs_modulus": 3.0e5},
           "sigma": {"gel.youngs_modulus": None}, "sigma_robust": {"gel.youngs_modulus": None}, "robust_method": None,
           "dt": 0.02}
    text = write_run_report(tmp_path, DemoResult(run_dir=tmp_path, recorded_bag=tmp_path / "bag", fit=fit), {}).read_text()
    assert "| gel.youngs_modulus | 3e+05 | 2.8e+05 | - | - | - |" in text and "(not computed, sysid.covariance)" in text
