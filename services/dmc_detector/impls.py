"""The implementations of the ``dmc_detector`` role, by name."""

from __future__ import annotations

from .service import DmcDetectorService, ThresholdDmcDetector

IMPLEMENTATIONS: dict[str, type[DmcDetectorService]] = {
    "threshold": ThresholdDmcDetector,
}
DEFAULT_IMPL = "threshold"


def pop_impl_arg(argv: list[str]) -> tuple[str, list[str]]:
    """Take ``--impl NAME`` / ``--impl=NAME`` out of argv; unknown names exit with the known ones."""
    impl, rest, i = DEFAULT_IMPL, [], 0
    while i < len(argv):
        a = argv[i]
        if a == "--impl" and i + 1 < len(argv):
            impl, i = argv[i + 1], i + 2
            continue
        if a.startswith("--impl="):
            impl = a.split("=", 1)[1]
        else:
            rest.append(a)
        i += 1
    if impl not in IMPLEMENTATIONS:
        raise SystemExit(f"dmc_detector: unknown --impl {impl!r}; known: {', '.join(IMPLEMENTATIONS)}")
    return impl, rest
