"""Writing the dataset: one frame at a time (``frame``: viewpoint, labels, scan, KITTI files, frame record), the
train/val/test splits (``splits``), and the orchestration behind ``mpchair generate`` (``generate``: seeds, worker
processes, shards, resume after SIGKILL, progress, the manifest written last). Scans and boxes are in the sensor frame
(x forward, y left, z up, metres), poses map sensor → world (Matterport, z up, metres).
"""

from mpchair.dataset.generate import GenerateRequest, GenerateSummary, generate
from mpchair.dataset.splits import SPLIT_MODES, split_frames

__all__ = ["SPLIT_MODES", "GenerateRequest", "GenerateSummary", "generate", "split_frames"]
