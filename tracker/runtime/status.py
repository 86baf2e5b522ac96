"""What a person watching needs to know per object, frame by frame: tracked (a pose it
trusts), uncertain (a pose below the confidence threshold), lost (tracked before, not now) or
not seen yet; as a line of text for the viewer and as counts for the run's summary."""
from __future__ import annotations


class TrackStatus:
    def __init__(self, names: dict[int, str], obj_ids, min_confidence: float):
        self.names = {o: names.get(o, str(o)) for o in obj_ids}
        self.min_confidence = float(min_confidence)
        self.counts = {o: {"tracked": 0, "uncertain": 0, "not_found": 0} for o in self.names}
        self.last_tracked: dict[int, int] = {}
        self.state = {o: "not seen" for o in self.names}

    def update(self, index: int, poses) -> str:
        """This frame's poses (its confidences in ``score``); returns the status text."""
        best = {}
        for p in poses:
            if p.obj_id in self.names and (p.obj_id not in best or p.score > best[p.obj_id].score):
                best[p.obj_id] = p
        for o in self.names:
            p = best.get(o)
            if p is not None and p.score >= self.min_confidence:
                self.counts[o]["tracked"] += 1
                self.last_tracked[o] = index
                self.state[o] = "tracked"
            else:
                self.counts[o]["uncertain" if p is not None else "not_found"] += 1
                if p is not None:
                    self.state[o] = "uncertain"
                else:
                    self.state[o] = "lost" if o in self.last_tracked else "not seen"
        parts = []
        for st in ("tracked", "uncertain"):
            items = [f"{self.names[o]} {best[o].score:.2f}" for o in self.names if self.state[o] == st]
            if items:
                parts.append(f"{st}: " + ", ".join(items))
        lost = [f"{self.names[o]} (last tracked at frame {self.last_tracked[o]})" for o in self.names
                if self.state[o] == "lost"]
        if lost:
            parts.append("LOST: " + ", ".join(lost))
        unseen = [self.names[o] for o in self.names if self.state[o] == "not seen"]
        if unseen:
            parts.append("not seen: " + ", ".join(unseen))
        return f"frame {index}\n" + "\n".join(parts)

    def summary(self) -> dict:
        """Per object name: frames tracked / uncertain / not found, the state at the end and
        the last frame it was tracked in (None: never)."""
        return {self.names[o]: dict(self.counts[o], state_at_end=self.state[o],
                                    last_tracked_frame=self.last_tracked.get(o))
                for o in self.names}
