"""Episode selections for every CLI here: LeRobot's list syntax (`[0,1,2]`) or a range ("0-19", "0-4,10")."""

from lerobot_pacdp.cli_errors import UserInputError

# A CLI field of this type takes `--episodes=[0,1,2]` (draccus decodes a list) or `--episodes=0-19`.
EpisodeSelection = list[int] | str

# More episodes than any LeRobot dataset holds: a typo such as 0-30000000 is refused before it is
# expanded into a list that does not fit in memory.
MAX_EPISODES = 1_000_000


class EpisodeSelectionError(UserInputError):
    """An episode selection that cannot be parsed or does not fit the dataset."""


def parse_episodes(spec: str, num_episodes: int | None = None) -> list[int]:
    """Parse an episode selection such as "0-19", "0,1,2" or "0-4,10" (ranges are inclusive).

    With `num_episodes`, an index outside 0..num_episodes-1 is refused, naming the part that holds it.
    """
    limit = MAX_EPISODES if num_episodes is None else num_episodes
    bounds: list[tuple[int, int]] = []
    for part in spec.split(","):
        first, dash, last = part.strip().partition("-")
        try:
            start, stop = int(first), int(last) if dash else int(first)
        except ValueError:
            raise EpisodeSelectionError(
                f"cannot parse episode selection {spec!r}; use a range like 0-19 or a list like 0,1,2."
            ) from None
        if stop < start:
            raise EpisodeSelectionError(
                f"episode range {part.strip()!r} ends before it starts; write it as {stop}-{start}."
            )
        if stop >= limit:
            if num_episodes is None:
                available = f"no dataset has more than {MAX_EPISODES} episodes"
            else:
                available = f"the dataset has {num_episodes} episodes (0-{num_episodes - 1})"
            raise EpisodeSelectionError(f"episode selection {part.strip()!r} is out of range: {available}.")
        bounds.append((start, stop))
    return [index for start, stop in bounds for index in range(start, stop + 1)]


def selected_episodes(selection: EpisodeSelection, num_episodes: int | None = None) -> list[int]:
    """The episode indices of a CLI selection: a list as given, a range parsed ("" selects none)."""
    if isinstance(selection, str):
        return parse_episodes(selection, num_episodes) if selection.strip() else []
    return parse_episodes(",".join(str(int(e)) for e in selection), num_episodes) if selection else []
