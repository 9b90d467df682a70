"""One-sample latency of the end-to-end policy: shipped ONNX (onnxruntime), torch, and a float32 export."""

from __future__ import annotations

import statistics
import tempfile
import time
from collections.abc import Callable

import numpy as np
import torch

from policies.learning.evaluate import paper_case
from policies.learning.export import export_onnx, load_controller, load_planner
from policies.learning.networks import EndToEndPolicy
from policies.learning.onnx_runtime import OnnxModel, load_shipped, shipped_path


def median_call_us(fn: Callable[[], object], calls: int) -> float:
    """Median wall time of one call of ``fn`` (us) over ``calls`` calls, after 50 warm-up calls."""
    for _ in range(50):
        fn()
    times = []
    for _ in range(calls):
        start = time.perf_counter_ns()
        fn()
        times.append(time.perf_counter_ns() - start)
    return statistics.median(times) / 1e3


def e2e_input() -> np.ndarray:
    """One end-to-end input (1, 29): hovering at the start of the paper's test case, t = T / 2."""
    x17, _ = paper_case(3)
    return np.concatenate([np.zeros(12), x17[1]])[None, :]


def e2e_latencies_us(calls: int) -> dict[str, float]:
    """Median one-sample latency (us) of the shipped e2e.onnx through ``OnnxModel.run_one`` (``onnx``)
    and through a plain ``session.run`` (``onnx_session_run``), the same policy in torch float32
    (``torch``) and exported in float32 (``onnx_float32``, ``run_one``); one thread each. Each figure
    is the wall time of the Python call, input copy and output included."""
    x = e2e_input()
    shipped = load_shipped("e2e")
    one = x.astype(shipped.dtype)
    out = {"onnx": median_call_us(lambda: shipped.run_one(one), calls),
           "onnx_session_run": median_call_us(lambda: shipped.run(one), calls)}
    weights = shipped_path("e2e").parent
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        planner, controller = load_planner(weights / "planner.pt"), load_controller(weights / "controller.pt")
        policy = EndToEndPolicy(planner, controller)
        xt = torch.as_tensor(x, dtype=torch.float32)

        def run_torch() -> object:
            with torch.inference_mode():
                return policy(xt)

        out["torch"] = median_call_us(run_torch, calls)
    finally:
        torch.set_num_threads(threads)
    with tempfile.TemporaryDirectory() as tmp:
        fast = OnnxModel(export_onnx(policy, 29, f"{tmp}/e2e32.onnx", torch.float32))
        one32 = x.astype(np.float32)
        out["onnx_float32"] = median_call_us(lambda: fast.run_one(one32), calls)
    return out
