"""Torch-free inference of the exported networks through onnxruntime (what the onboard program runs)."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import numpy as np

WEIGHT_NAMES = ("planner", "controller", "e2e")


def shipped_path(name: str) -> Path:
    """Path of a shipped ONNX file in ``policies/weights`` (``planner``, ``controller`` or ``e2e``)."""
    if name not in WEIGHT_NAMES:
        raise ValueError(f"unknown network {name!r}; shipped: {', '.join(WEIGHT_NAMES)}")
    return Path(str(resources.files("policies") / "weights" / f"{name}.onnx"))


class OnnxModel:
    """One ONNX network on onnxruntime's CPU provider: ``predict(x)`` for (n_in,) or (N, n_in) inputs."""

    def __init__(self, path: str | Path, threads: int = 1) -> None:
        import onnxruntime as ort

        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"no ONNX model at {path}")
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = threads
        opts.inter_op_num_threads = 1
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        self.path = path
        self.session = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
        inp, out = self.session.get_inputs()[0], self.session.get_outputs()[0]
        self.input_name, self.output_name = inp.name, out.name
        self.n_inputs = int(inp.shape[-1])
        self.n_outputs = int(out.shape[-1])
        self.dtype = np.float64 if inp.type == "tensor(double)" else np.float32

    def run(self, x: np.ndarray) -> np.ndarray:
        """Outputs (N, n_out) for inputs (N, n_in) of ``self.dtype``, without checks (the fast path)."""
        return self.session.run([self.output_name], {self.input_name: x})[0]

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
        out = self.run(np.ascontiguousarray(batch, dtype=self.dtype)).astype(np.float64)
        return out[0] if single else out


def load_shipped(name: str, threads: int = 1) -> OnnxModel:
    """The shipped network ``name`` (``planner``, ``controller`` or ``e2e``) on onnxruntime."""
    path = shipped_path(name)
    if not path.is_file():
        raise FileNotFoundError(f"the shipped {name} network is missing ({path}); train and export it with "
                                "`hil train`")
    return OnnxModel(path, threads)
