"""What the robot touches in a ``GraspClutter-v1`` scene: the table, an object, or itself.

The watched body pairs, per sub-scene: every robot link but the base (``panda_link0``, which
stands on the table) against the table, each object and every other such link. A pair touches
when the simulator reports a non-zero contact impulse between its bodies: on the CPU one pass
over the contact list, on the GPU one contact-pair impulse query (made on first use).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

BASE_LINK = "panda_link0"
"""The robot link left out of contact checks (it stands on the table)."""


@dataclass
class RobotContactPairs:
    """The watched body pairs of one scene (all sub-scenes), built once per scene.

    ``pairs``: ``(robot body, other body)``; ``labels``: each pair's ``(sub-scene, kind)``;
    ``index``: a pair (as a set of bodies) to its position; ``query``: the GPU impulse query.
    """

    pairs: list[tuple]
    labels: list[tuple[int, str]]
    index: dict[frozenset, int]
    num_envs: int
    query: Any = None

    @classmethod
    def build(cls, links: list, table, objects: list[list]) -> RobotContactPairs:
        """From the robot's ``links``, the ``table`` actor and ``objects[i]``, the object actors of sub-scene i."""
        links = [link for link in links if link.name != BASE_LINK]
        pairs: list[tuple] = []
        labels: list[tuple[int, str]] = []
        for i in range(len(objects)):
            bodies = [link._bodies[i] for link in links]
            others = [(table._bodies[i], "table")]
            others += [(obj._bodies[0], "object") for obj in objects[i]]
            for a, body in enumerate(bodies):
                pairs += [(body, other) for other, _ in others] + [(body, b) for b in bodies[a + 1:]]
                labels += [(i, kind) for _, kind in others] + [(i, "self")] * (len(bodies) - a - 1)
        index = {frozenset(pair): n for n, pair in enumerate(pairs)}
        return cls(pairs, labels, index, len(objects))

    def touching_kinds(self, scene) -> list[set[str]]:
        """Per sub-scene, the subset of ``{"table", "object", "self"}`` the robot touches now in ``scene``."""
        if scene.gpu_sim_enabled:
            if self.query is None:
                self.query = scene.px.gpu_create_contact_pair_impulse_query(self.pairs)
            scene.px.gpu_query_contact_pair_impulses(self.query)
            touching = (self.query.cuda_impulses.torch().norm(dim=-1) > 0).cpu().tolist()
        else:
            touching = [False] * len(self.pairs)
            for contact in scene.px.get_contacts():
                n = self.index.get(frozenset(contact.bodies))
                if n is not None and any(np.linalg.norm(point.impulse) > 0 for point in contact.points):
                    touching[n] = True
        kinds: list[set[str]] = [set() for _ in range(self.num_envs)]
        for (i, kind), hit in zip(self.labels, touching):
            if hit:
                kinds[i].add(kind)
        return kinds
