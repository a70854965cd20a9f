"""Deploying PointPillars: the network exported to ONNX / OpenVINO IR and run in ONNX Runtime or OpenVINO, in fp32,
bf16 or int8, with voxelization, scatter, the rulebook tables and box decoding + NMS outside the graph.

- :mod:`detector.deploy.extra`: the optional ``deploy`` extra, or a one-line error naming ``pip install '.[deploy]'``;
- :mod:`detector.deploy.cpu`: which precisions this CPU computes natively (``/proc/cpuinfo`` flags);
- :mod:`detector.deploy.dense_graph`: the dense network from the canvas, BatchNorm folded;
- :mod:`detector.deploy.sparse_graph`: the sparse network over rulebook tables given as inputs (Gather + MatMul);
- :mod:`detector.deploy.export`: tracing to ONNX, conversion to OpenVINO IR;
- :mod:`detector.deploy.runtimes`: ONNX Runtime and OpenVINO sessions;
- :mod:`detector.deploy.quantize`: post-training int8 (NNCF for OpenVINO, ONNX Runtime's quantizer);
- :mod:`detector.deploy.deployed`: a deployed model with :class:`detector.models.PointPillars`'s stage methods;
- :mod:`detector.deploy.folder`: ``detector export``'s output folder.

See ``docs/deployment.md``.
"""
