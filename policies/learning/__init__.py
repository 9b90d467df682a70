"""Imitation learning: training data, networks, losses, training, ONNX export and onnxruntime inference.

Torch is imported only by ``networks``, ``deploy``, ``losses``, ``train``, ``export`` and ``latency``;
``features``, ``data``, ``evaluate``, ``onnx_runtime`` and ``learned_pilots`` are torch-free and are what the
onboard program uses (torch is for training and export only).
"""
