"""phm_torch: real-time diagnostics and prognostics of electromechanical actuators in PyTorch."""

__version__ = "0.1.0"
