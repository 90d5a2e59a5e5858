"""IFNet point-cloud registration.

This package stays importable without torch: `model.geometry` (NumPy only) is shared with the
service. The network lives in `model.ifnet`, its torch geometry in `model.ops`.
"""
