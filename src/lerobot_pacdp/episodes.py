"""Episode selections written the way people type them ("0-19", "0,1,2", "0-4,10"), for every CLI here."""


class EpisodeSelectionError(ValueError):
    """An episode selection that cannot be parsed."""


def parse_episodes(spec: str) -> list[int]:
    """Parse an episode selection such as "0-19", "0,1,2" or "0-4,10" (ranges are inclusive)."""
    indices: list[int] = []
    for part in spec.split(","):
        first, dash, last = part.strip().partition("-")
        try:
            indices.extend(range(int(first), int(last) + 1) if dash else [int(first)])
        except ValueError:
            raise EpisodeSelectionError(
                f"cannot parse episode selection {spec!r}; use a range like 0-19 or a list like 0,1,2."
            ) from None
    return indices
