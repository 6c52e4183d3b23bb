"""The twin's methods: a pose source and a combination each, named like the fusion registry's methods
(:mod:`traffictwin.fusion.methods`); the table is here, the work in :mod:`traffictwin.twin.fuse`."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["TwinMethod", "TWIN_METHODS"]


@dataclass(frozen=True)
class TwinMethod:
    """A twin method: ``pose`` in (``noisy``, ``registered``, ``learned``), ``combine`` in
    (``dempster``, ``network``); ``needs`` the models it loads (``registration``, ``fusion``)."""

    name: str
    pose: str
    combine: str

    @property
    def needs(self) -> tuple[str, ...]:
        return tuple(
            n
            for n, used in (
                ("registration", self.pose == "learned"),
                ("fusion", self.combine == "network"),
            )
            if used
        )


TWIN_METHODS: dict[str, TwinMethod] = {
    m.name: m
    for m in (
        TwinMethod("naive", "noisy", "dempster"),
        TwinMethod("registered", "registered", "dempster"),
        TwinMethod("learned", "learned", "dempster"),
        TwinMethod("dnn", "noisy", "network"),
        TwinMethod("registered+network", "registered", "network"),
        TwinMethod("learned+network", "learned", "network"),
    )
}
