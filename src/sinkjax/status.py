"""One enumeration of what can happen to a frame, with a message per member.

As ``optimistix.RESULTS`` does for solvers: every estimator, the pipeline, calibration and the
torch bridge report a frame's outcome as a :class:`Status`. Inside JAX a status travels as its
integer :attr:`Status.code` (an ``Int[Array, ""]``); everywhere else it is the member itself,
which is also the string written in the results CSV's ``status`` column (docs/conventions.md §4).
"""

from __future__ import annotations

import enum


class Status(enum.StrEnum):
    """A frame's outcome. ``str(status)`` is the CSV code; :attr:`message` the default words."""

    OK = "ok"
    NO_CONTACT = "no_contact"
    NO_WHEEL = "no_wheel"
    FIT_FAILED = "fit_failed"
    BAD_RECT = "bad_rect"
    BAD_IMAGE = "bad_image"
    UNREADABLE = "unreadable"
    ERROR = "error"
    IMPLAUSIBLE = "implausible"

    @property
    def code(self) -> int:
        """The integer that stands for this status inside JAX (``jnp.where`` chains)."""
        return _CODES[self]

    @classmethod
    def from_code(cls, code: int) -> Status:
        """The member whose :attr:`code` is ``code``. Raises ValueError for an unknown code."""
        try:
            return _MEMBERS[int(code)]
        except (IndexError, ValueError) as e:
            raise ValueError(f"no status has code {code!r}") from e

    @property
    def measured(self) -> bool:
        """True for the statuses that carry a measurement (``ok`` and ``no_contact``)."""
        return self in (Status.OK, Status.NO_CONTACT)

    @property
    def message(self) -> str:
        """What the status means, in words, with what to do about it."""
        return _MESSAGES[self]


_MEMBERS: tuple[Status, ...] = tuple(Status)
_CODES: dict[Status, int] = {s: i for i, s in enumerate(_MEMBERS)}
_MESSAGES: dict[Status, str] = {
    Status.OK: "",
    Status.NO_CONTACT: "the soil does not reach inside the rim (no wheel-soil boundary)",
    Status.NO_WHEEL: (
        "no rim circle found: too few wheel-coloured edge pixels on a circle; check the "
        "confidence rectangle lies on the wheel face and the segmentation thresholds"
    ),
    Status.FIT_FAILED: (
        "the circle-plus-line fit did not converge; the frame may be blurred or "
        "the soil and wheel colours too similar"
    ),
    Status.BAD_RECT: (
        "the confidence rectangle is not inside the image; fix confidence_rect in the rig "
        "file or pass --confidence-rect X,Y,W,H"
    ),
    Status.BAD_IMAGE: "the image cannot be measured (too small or an unsupported pixel type)",
    Status.UNREADABLE: "the file could not be read or decoded as an image",
    Status.ERROR: "the estimator raised an error on this frame",
    Status.IMPLAUSIBLE: (
        "the fitted rim and boundary do not explain the image (the segmentation did not "
        "understand this frame); the values are shown but not trustworthy: calibrate the "
        "segmentation on a few labelled frames"
    ),
}
