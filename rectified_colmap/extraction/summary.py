"""What an extraction did, image by image: the :class:`Summary` that ``extract`` returns."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

from ..io.images import ImageError

logger = logging.getLogger(__package__)


def error_message(e: Exception) -> str:
    """The one-line message of a per-image failure: an ImageError's cause as it is, any
    other exception with its type."""
    return str(e) if isinstance(e, ImageError) else f"{type(e).__name__}: {e}"


@dataclass
class Summary:
    """Per image, what the run did with it; :meth:`report` writes it up in lines."""

    done: list[str] = field(default_factory=list)
    """Images extracted in this run."""
    copied: dict[str, str] = field(default_factory=dict)
    """Images whose existing features were copied into the output that lacked them:
    name -> "database -> hloc" or "hloc -> database"."""
    skipped: list[str] = field(default_factory=list)
    """Images that already had features in every output."""
    failed: dict[str, str] = field(default_factory=dict)
    warnings: dict[str, list[str]] = field(default_factory=dict)
    plain: list[str] = field(default_factory=list)
    """Images that got plain SIFT (no depth or no usable plane)."""
    foreign: dict[str, int] = field(default_factory=dict)
    """Output path -> number of listed images whose features another extractor wrote."""
    deleted_matches: tuple[int, int] = (0, 0)
    """(match rows, two-view geometry rows) deleted by ``overwrite``."""
    num_keypoints: int = 0
    seconds: float = 0.0
    work_seconds: float = 0.0
    """Seconds spent extracting (after planning and copies): the throughput's base."""

    @property
    def ok(self) -> bool:
        return not self.failed

    def warn(self, name: str, message: str) -> None:
        self.warnings.setdefault(name, []).append(message)
        logger.warning("%s: %s", name, message)

    def fail(self, name: str, message: str) -> None:
        """Record (and log at ERROR) that ``name`` failed; the run goes on."""
        self.failed[name] = message
        logger.error("%s: %s", name, message)

    def report(self) -> str:
        n = len(self.done)
        lines = [
            f"images: {n} extracted, {len(self.copied)} copied between outputs, "
            f"{len(self.skipped)} skipped (already had features), "
            f"{len(self.failed)} failed"
        ]
        if n:
            lines += [
                f"keypoints: {self.num_keypoints} in the {n} extracted image(s) "
                f"({self.num_keypoints / n:.0f} per image)",
                f"plain SIFT only: {len(self.plain)} of the {n} extracted image(s) (no depth "
                "or no plane worth rectifying)",
                f"time: {self.seconds:.1f} s ({self.seconds / n:.2f} s per extracted image, "
                f"{n / self.work_seconds if self.work_seconds > 0 else 0:.2f} images/s "
                "while extracting)",
            ]
        else:
            lines.append(
                f"nothing extracted in this run (time: {self.seconds:.1f} s); the outputs "
                "keep the features they had"
                + ("; --overwrite re-extracts" if self.skipped or self.copied else "")
            )
        lines += [
            f"kept {k} image(s) with features from another extractor in {path}"
            for path, k in self.foreign.items()
            if k
        ]
        if any(self.deleted_matches):
            lines.append(
                f"deleted {self.deleted_matches[0]} match and "
                f"{self.deleted_matches[1]} two-view geometry rows (--overwrite)"
            )
        lines += [f"WARNING {name}: {w}" for name, ws in self.warnings.items() for w in ws]
        lines += [f"FAILED {name}: {why}" for name, why in self.failed.items()]
        return "\n".join(lines)
