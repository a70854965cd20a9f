"""mpchair: build the Matterport-Chair 3D detection dataset (KITTI format) from Matterport3D house meshes.

Stages, one folder each: ``matterport/`` (read the release format), ``synth/`` (procedural houses in that format),
``scan/`` (sensors, viewpoints, raycasting), ``labels/`` (boxes and filters), ``dataset/`` (KITTI writer,
orchestration). The shared floor used by both ``mpchair`` and ``detector``: ``geometry/`` (frames, boxes, pillars),
``kitti/`` (KITTI file formats), ``errors``, ``atomic`` and ``config``.
"""

__version__ = "0.1.0"
