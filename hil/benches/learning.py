"""Bench group `learning`: shipped end-to-end policy latency (onnxruntime and torch, one sample) and the
rate of labelled planner training samples."""

from __future__ import annotations

from collections.abc import Iterator

from hil.benches import BenchRow
from policies.learning.data import planner_samples_per_s


def collect(quick: bool) -> Iterator[BenchRow]:
    try:
        from policies.learning.latency import e2e_latencies_us  # (torch, onnxruntime: the 'learn' extra)
    except ImportError:  # torch/onnxruntime are the optional 'learn' extra
        return
    lat = e2e_latencies_us(500 if quick else 5000)
    yield BenchRow("e2e_inference_us", lat["onnx"], "us",
                   "shipped e2e.onnx (float64 in/out and physical units, float32 hidden layers), onnxruntime "
                   "CPU, 1 thread: wall time of one OnnxModel.run_one call (29 inputs copied into bound "
                   "buffers, graph run, 3 outputs), one sample, median")
    yield BenchRow("e2e_session_run_us", lat["onnx_session_run"], "us",
                   "the same file through a plain InferenceSession.run call (feed dict, output allocated), "
                   "one sample, median")
    yield BenchRow("e2e_torch_inference_us", lat["torch"], "us",
                   "the same policy in torch (float32, 1 thread, inference mode), one sample, median")
    yield BenchRow("e2e_float32_inference_us", lat["onnx_float32"], "us",
                   "the policy exported all in float32 (not shipped: misses 1e-5 parity), run_one, median")
    n = 20_000 if quick else 200_000
    yield BenchRow("planner_samples_per_s", planner_samples_per_s(n), "samples/s",
                   f"labelled, augmented planner samples (primitive closed form), numpy, one batch of {n:,}")
