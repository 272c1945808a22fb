"""The sysid node over real DDS (loopback): ~/fit, the transient-local result, applying to a live sim node."""

from __future__ import annotations

import json
import math
import threading

import pytest
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_msgs.msg import String
from std_srvs.srv import Trigger

from sim_core.errors import ConfigError
from tests.thinshell_ros.conftest import spin_until
from tests.thinshell_ros.fake_sim import FakeSimulation
from thinshell_ros.sim_node import SimNode
from sysid.fit_recording import FitOptions
from thinshell_ros.sysid_node import RESULT_QOS, FitRequest, SysidNode, parse_params

pytestmark = pytest.mark.ros


class Harness:
    """Sim node + sysid node + a client node on one executor."""

    def __init__(self, ctx, runner, sim=None, **params) -> None:
        self.sim = SimNode(sim=sim or FakeSimulation(), context=ctx,
                           parameter_overrides=[Parameter("mode", value="stepped"), Parameter("mesh_rate", value=0.0)])
        self.node = SysidNode(runner=runner, context=ctx,
                              parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])
        self.client = Node("sysid_client", context=ctx)
        self.ex = SingleThreadedExecutor(context=ctx)
        for n in (self.sim, self.node, self.client):
            self.ex.add_node(n)

    def fit(self) -> Trigger.Response:
        cli = self.client.create_client(Trigger, "/thinshell_sysid/fit")
        assert cli.wait_for_service(timeout_sec=5.0)
        fut = cli.call_async(Trigger.Request())
        assert spin_until(self.ex, fut.done, 5.0)
        return fut.result()

    def late_result(self, timeout: float) -> dict:
        """Subscribe only now (transient local) and return the first result received."""
        got: list[dict] = []
        self.client.create_subscription(String, "/thinshell/sysid/result", lambda m: got.append(json.loads(m.data)),
                                        RESULT_QOS)
        assert spin_until(self.ex, lambda: bool(got), timeout), "no result on /thinshell/sysid/result"
        return got[0]

    def close(self) -> None:
        self.ex.shutdown(timeout_sec=0)
        for n in (self.client, self.node, self.sim):
            n.destroy_node()


def test_fit_result_is_latched_and_applied_to_the_sim_node(ros_context, tmp_path):
    release = threading.Event()
    seen: list[FitRequest] = []

    def runner(job: FitRequest) -> dict:
        seen.append(job)
        assert release.wait(10.0)
        return {"params": {"contact.stiffness": 2500.0}, "fit_status": "converged"}

    h = Harness(ros_context, runner, bag=str(tmp_path), params="contact.stiffness", apply_to="/thinshell_sim",
                t_max=0.5, out=str(tmp_path / "rep"))
    try:
        res = h.fit()
        assert res.success and "fit started" in res.message
        busy = h.fit()  # the node keeps spinning while the worker runs, and refuses a second fit
        assert not busy.success and "already running" in busy.message
        release.set()
        assert spin_until(h.ex, lambda: bool(h.node.results), 10.0)
        assert h.sim.sim.get_parameter("contact.stiffness") == 2500.0
        assert h.sim.get_parameter("contact.stiffness").value == 2500.0
        result = h.late_result(5.0)
        assert result["status"] == "ok" and result["params"] == {"contact.stiffness": 2500.0}
        assert result["applied"] == {"contact.stiffness": True} and result["apply_to"] == "/thinshell_sim"
        job = seen[0]
        assert job.bag == tmp_path and job.out == tmp_path / "rep" and not job.force
        # the fitter's defaults else, but for the calibration's replays in this process (no fork beside DDS threads)
        assert job.options == FitOptions(params=("contact.stiffness",), t_max=0.5, probe_worker=False)
        assert not h.node.busy
    finally:
        h.close()


def test_rejected_value_and_failed_fit_are_reported(ros_context, tmp_path):
    values = iter([{"params": {"contact.stiffness": -1.0}}, RuntimeError("replay diverged")])

    def runner(job: FitRequest) -> dict:
        v = next(values)
        if isinstance(v, Exception):
            raise v
        return v

    h = Harness(ros_context, runner, bag=str(tmp_path), apply_to="/thinshell_sim")
    try:
        assert h.fit().success
        assert spin_until(h.ex, lambda: len(h.node.results) == 1, 10.0)
        first = h.node.results[0]
        assert first["applied"] == {"contact.stiffness": False} and "must be > 0" in first["apply_message"]
        assert h.sim.sim.get_parameter("contact.stiffness") == 1000.0  # the sim node kept its value
        assert h.fit().success
        assert spin_until(h.ex, lambda: len(h.node.results) == 2, 10.0)
        result = h.late_result(5.0)  # only the last result is kept
        assert result["status"] == "error" and "replay diverged" in result["error"] and result["applied"] is None
    finally:
        h.close()


def test_missing_target_times_out_and_bad_requests_are_refused(ros_context, tmp_path):
    h = Harness(ros_context, lambda job: {"params": {"contact.stiffness": 2.0}}, bag=str(tmp_path / "absent"),
                apply_to="/nobody", apply_timeout=0.3)
    try:
        res = h.fit()
        assert not res.success and "does not exist" in res.message
        h.node.set_parameters([Parameter("bag", value=str(tmp_path))])
        assert h.fit().success
        assert spin_until(h.ex, lambda: bool(h.node.results), 5.0)
        assert "/nobody/set_parameters not available" in h.node.results[0]["apply_message"]
        h.node.set_parameters([Parameter("bag", value=""), Parameter("params", value="a,b,a")])
        assert "'bag' is empty" in h.fit().message
        h.node.set_parameters([Parameter("bag", value=str(tmp_path)), Parameter("params", value=""),
                               Parameter("gel_resolution", value="3,x,2")])
        assert "'gel_resolution' must be NX,NY,NZ" in h.fit().message
        h.node.set_parameters([Parameter("gel_resolution", value="3,3"), Parameter("max_nfev", value=0)])
        assert "FitOptions: max_nfev must be >= 1" in h.fit().message
        h.node.set_parameters([Parameter("max_nfev", value=30), Parameter("gel_resolution", value=""),
                               Parameter("gel_element", value="hooke")])
        assert "gel_element must be one of stable_neohookean" in h.fit().message
    finally:
        h.close()
    with pytest.raises(ConfigError, match=r"lists \['a'\] more than once"):
        parse_params("a, b,a")
    assert parse_params(" sheet.density, ,gel.youngs_modulus") == ("sheet.density", "gel.youngs_modulus")


@pytest.fixture(scope="module")
def heavy_card_bag(tmp_path_factory):
    """A 40 ms headless recording of the bundled scene with the card's density at 1000 kg/m^3
    (its ``scene.yaml`` keeps the nominal 700): the card sags faster than the nominal model says."""
    from sim_core.simulation import Simulation
    from sysid.bagio import BagWriter
    from thinshell_ros.headless import run_headless, scene_trajectory
    from thinshell_ros.paths import bundled_scene

    sim = Simulation.from_scene(bundled_scene())
    assert sim.get_parameter("sheet.density") == 700.0
    sim.set_parameter("sheet.density", 1000.0)
    path = tmp_path_factory.mktemp("sysid_node") / "heavy_card"
    with BagWriter(path, scene=bundled_scene()) as bag:
        run_headless(sim, scene_trajectory(sim, "press_slide"), bag, duration=0.04)
    return path


def test_real_fit_is_published_and_applied_to_a_live_sim_node(ros_context, heavy_card_bag, tmp_path):
    """The real fitter (:func:`sysid.fit_recording.fit_recording`) through ~/fit: the result arrives on the latched topic
    with the recording's density 1000 inside the reported robust 2-sigma interval around the fitted value (40 ms of a
    card at rest on the table barely tell its density: the robust sigma, never below the formal Gauss-Newton one
    (:meth:`sysid.covariance.RobustCovariance.floored`), is of the order of the nominal 700), and the sim node takes
    the value."""
    from sim_core.simulation import Simulation
    from thinshell_ros.paths import bundled_scene
    from thinshell_ros.sysid_node import run_fit

    sim = Simulation.from_scene(bundled_scene())
    out = tmp_path / "fit"
    h = Harness(ros_context, run_fit, sim=sim, bag=str(heavy_card_bag), params="sheet.density",
                out=str(out), t_max=0.04, dt=0.01, max_nfev=2, gel_resolution="3,3,2",
                apply_to="/thinshell_sim", write_scene=str(tmp_path / "fitted.yaml"))
    try:
        assert h.fit().success
        assert spin_until(h.ex, lambda: bool(h.node.results), 120.0), "fit did not finish"
        result = h.late_result(5.0)
        assert result["status"] == "ok", result
        rho = result["params"]["sheet.density"]
        assert result["initial"] == {"sheet.density": 700.0}
        sigma = result["sigma_robust"]["sheet.density"]
        assert result["robust_method"] == "hac+nuisance" and math.isfinite(sigma), result
        assert sigma >= result["sigma"]["sheet.density"] > 0.0, result
        assert abs(rho - 1000.0) < 2.0 * sigma, (rho, sigma)
        assert result["applied"] == {"sheet.density": True}
        assert h.sim.get_parameter("sheet.density").value == pytest.approx(rho)
        assert sim.get_parameter("sheet.density") == pytest.approx(rho)
        assert {"fit.json", "report.html", "report.md"} <= set(result["files"]) and result["out"] == str(out)
        assert result["scene"] == str(tmp_path / "fitted.yaml")  # the fitted scene, loadable, with the value
        assert Simulation.from_scene(result["scene"]).get_parameter("sheet.density") == pytest.approx(rho)
    finally:
        h.close()


def test_recording_map_parameter_reaches_the_fit(ros_context, tmp_path):
    jobs: list = []
    h = Harness(ros_context, lambda job: jobs.append(job) or {"params": {}}, bag=str(tmp_path),
                recording_map=str(tmp_path / "absent.yaml"))
    try:
        assert "parameter 'recording_map': " in h.fit().message
        (tmp_path / "recording.yaml").write_text("version: 1\n")
        h.node.set_parameters([Parameter("recording_map", value=str(tmp_path / "recording.yaml"))])
        assert h.fit().success
        assert spin_until(h.ex, lambda: bool(jobs), 5.0)
        assert jobs[0].options.recording_map == str(tmp_path / "recording.yaml")
    finally:
        h.close()
