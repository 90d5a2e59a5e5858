"""ONNX export of IFNet with the time-step/iteration loop unrolled, and its self-check."""
