"""Sparse 3D convolution: a pure-PyTorch backend and an optional spconv backend.

Layers take and return :class:`omnilidar.sparse.tensor.SparseTensor`; weights use
spconv's layout ``(out, kD, kH, kW, in)`` in both backends. Pick a backend with
:func:`omnilidar.sparse.backend.conv_layers` (``"torch"``, ``"spconv"`` or
``"auto"``). Nothing is imported here: import the module you use (``tensor``,
``conv``, ``backend``), so that a stage's code hash covers only that.
"""
