"""Torch-free inference of the exported networks through onnxruntime (what the onboard program runs)."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import numpy as np

WEIGHT_NAMES = ("planner", "controller", "e2e", "e2e_rl")


def shipped_path(name: str) -> Path:
    """Path of a shipped ONNX file in ``policies/weights`` (one of `WEIGHT_NAMES`)."""
    if name not in WEIGHT_NAMES:
        raise ValueError(f"unknown network {name!r}; shipped: {', '.join(WEIGHT_NAMES)}")
    return Path(str(resources.files("policies") / "weights" / f"{name}.onnx"))


class OnnxModel:
    """One ONNX network on onnxruntime's CPU provider: ``predict(x)`` for (n_in,) or (N, n_in) inputs.

    The session runs sequentially on ``threads`` intra-op threads with every graph optimisation and no
    spinning worker threads. One-sample calls (``run_one``, and ``predict`` of a single input) go
    through input/output buffers bound to the session once, so a call copies 29 numbers in and runs:
    no per-call allocation or name lookup. An instance is therefore not safe to share between threads.
    """

    def __init__(self, path: str | Path, threads: int = 1) -> None:
        import onnxruntime as ort

        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"no ONNX model at {path}")
        if threads < 1:
            raise ValueError("threads must be >= 1")
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = threads
        opts.inter_op_num_threads = 1
        opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
        opts.add_session_config_entry("session.inter_op.allow_spinning", "0")
        self.path = path
        self.session = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
        inp, out = self.session.get_inputs()[0], self.session.get_outputs()[0]
        self.input_name, self.output_name = inp.name, out.name
        self.n_inputs = int(inp.shape[-1])
        self.n_outputs = int(out.shape[-1])
        self.dtype = np.float64 if inp.type == "tensor(double)" else np.float32
        # one-sample buffers, bound once (the session reads and writes them in place)
        self._one_in = np.zeros((1, self.n_inputs), self.dtype)
        self._one_out = np.zeros((1, self.n_outputs), self.dtype)
        self._binding = self.session.io_binding()
        self._binding.bind_input(self.input_name, "cpu", 0, self.dtype, self._one_in.shape,
                                 self._one_in.ctypes.data)
        self._binding.bind_output(self.output_name, "cpu", 0, self.dtype, self._one_out.shape,
                                  self._one_out.ctypes.data)

    def run(self, x: np.ndarray) -> np.ndarray:
        """Outputs (N, n_out) for inputs (N, n_in) of ``self.dtype``, without checks."""
        return self.session.run([self.output_name], {self.input_name: x})[0]

    def run_one(self, x: np.ndarray) -> np.ndarray:
        """Outputs (n_out,) for one input (n_in,) or (1, n_in), without checks (the one-sample fast
        path). The result is the bound output buffer: copy it to keep it past the next call."""
        np.copyto(self._one_in[0], np.reshape(x, -1), casting="unsafe")
        self.session.run_with_iobinding(self._binding)
        return self._one_out[0]

    def predict(self, x: object) -> np.ndarray:
        """Outputs (float64) for inputs (n_in,) or (N, n_in); raises ValueError on a wrong shape or
        non-finite values."""
        arr = np.asarray(x, dtype=np.float64)
        single = arr.ndim == 1
        batch = arr[None, :] if single else arr
        if batch.ndim != 2 or batch.shape[1] != self.n_inputs:
            raise ValueError(f"{self.path.name} takes inputs of shape ({self.n_inputs},) or "
                             f"(N, {self.n_inputs}), got {arr.shape}")
        if not np.all(np.isfinite(batch)):
            raise ValueError(f"{self.path.name}: inputs must be finite")
        if single:
            return self.run_one(arr).astype(np.float64)
        return self.run(np.ascontiguousarray(batch, dtype=self.dtype)).astype(np.float64)


def load_shipped(name: str, threads: int = 1) -> OnnxModel:
    """The shipped network ``name`` (one of `WEIGHT_NAMES`) on onnxruntime."""
    path = shipped_path(name)
    if not path.is_file():
        raise FileNotFoundError(f"the shipped {name} network is missing ({path}); train and export it with "
                                "`hil train`")
    return OnnxModel(path, threads)
