"""d3lvo_deploy: the torch-free D3LVO runtime (KITTI I/O, geometry, evaluation, synthetic data).

A vehicle installs numpy, onnxruntime and opencv only, so nothing in this package imports torch.
"""

__version__ = "0.1.0"
