"""Fixed-capacity feature database (seed 000, sections II.D-E).

Parallel arrays over ``capacity`` slots (paper: 50); a slot is in use when ``active``. Feature ids
are monotonic int64, never reused, so the terrain map can tell a re-emitted feature from a new one.

Confidence index (section II.D): integer in ``[0, confidence_max]``, +1 when the feature is
matched, -1 when it is predicted inside the image but not matched. New features start at the
frame's initialisation index; an unmatched measurement replaces the feature with the lowest
confidence when that confidence is below the initialisation index.
"""

from __future__ import annotations

import numpy as np


class FeatureDatabase:
    """State of every stored feature.

    y (C, D) states; P (C, D, D) covariances; R_ref (C, 3, 3) constant reference rotation of the
    angles; origin (C, 3) camera centre at initialisation; confidence (C,) int; active (C,) bool;
    ids (C,) int64 (-1 when free); born_frame (C,) frame number of initialisation; updates (C,)
    number of accepted EKF updates; converged (C,) bool (set once, when first converged);
    template (C, K) the normalised patch of the feature's last accepted measurement (appearance
    check), has_template (C,) bool; edge (C,) bool: the feature is a point on an image edge
    (initialised from an edgel, matched to edgels only) and normal (C, 2) the edge's unit normal at
    its last match (docs/mapper.md, "Edgels").
    """

    def __init__(self, capacity: int, state_dim: int, template_size: int = 0):
        if capacity < 1:
            raise ValueError(f"feature database capacity must be >= 1, got {capacity}")
        self.capacity = int(capacity)
        self.state_dim = int(state_dim)
        self.y = np.zeros((capacity, state_dim))
        self.P = np.zeros((capacity, state_dim, state_dim))
        self.R_ref = np.broadcast_to(np.eye(3), (capacity, 3, 3)).copy()
        self.origin = np.zeros((capacity, 3))
        self.confidence = np.zeros(capacity, dtype=np.int32)
        self.active = np.zeros(capacity, dtype=bool)
        self.ids = np.full(capacity, -1, dtype=np.int64)
        self.born_frame = np.zeros(capacity, dtype=np.int64)
        self.updates = np.zeros(capacity, dtype=np.int32)
        self.converged = np.zeros(capacity, dtype=bool)
        self.template = np.zeros((capacity, int(template_size)), np.float32)
        self.has_template = np.zeros(capacity, dtype=bool)
        self.edge = np.zeros(capacity, dtype=bool)
        self.normal = np.zeros((capacity, 2))
        self._next_id = 0

    @property
    def n_active(self) -> int:
        return int(self.active.sum())

    def active_slots(self) -> np.ndarray:
        return self.active.nonzero()[0]

    def free_slots(self) -> np.ndarray:
        return (~self.active).nonzero()[0]

    def insert(
        self,
        slots: np.ndarray,
        y: np.ndarray,
        P: np.ndarray,
        R_ref: np.ndarray,
        origin: np.ndarray,
        confidence: int,
        frame: int,
        normal: np.ndarray | None = None,
    ) -> np.ndarray:
        """Store new features in ``slots`` (K,) (free or being replaced); returns their new ids (K,).
        ``normal (K, 2)``: the edge normal of each, zero for a corner (None: all corners)."""
        slots = np.asarray(slots, dtype=np.intp)
        k = len(slots)
        ids = np.arange(self._next_id, self._next_id + k, dtype=np.int64)
        self._next_id += k
        self.y[slots] = y
        self.P[slots] = P
        self.R_ref[slots] = R_ref
        self.origin[slots] = origin
        self.confidence[slots] = confidence
        self.active[slots] = True
        self.ids[slots] = ids
        self.born_frame[slots] = frame
        self.updates[slots] = 0
        self.converged[slots] = False
        self.has_template[slots] = False
        if normal is None:
            self.edge[slots] = False
            self.normal[slots] = 0.0
        else:
            normal = np.asarray(normal, dtype=float).reshape(k, 2)
            self.normal[slots] = normal
            self.edge[slots] = (normal != 0.0).any(axis=1)
        return ids

    def remove(self, slots: np.ndarray) -> None:
        slots = np.asarray(slots, dtype=np.intp)
        self.active[slots] = False
        self.ids[slots] = -1

    def adjust_confidence(self, matched: np.ndarray, unmatched: np.ndarray, confidence_max: int) -> None:
        """+1 for ``matched`` slots, -1 for ``unmatched`` (visible) slots, clipped to [0, max]."""
        self.confidence[matched] += 1
        self.confidence[unmatched] -= 1
        np.minimum(np.maximum(self.confidence, 0, out=self.confidence), confidence_max, out=self.confidence)

    def clear(self) -> None:
        self.active[:] = False
        self.ids[:] = -1
