"""Trained drivers that ship with drivelab, and the model cards that vouch for them.

A driver is a directory (package data under ``drivelab/drivers/NAME/``, or one a user downloaded)
holding a policy as ``TrainedPolicy.save`` writes it (``tensors.safetensors``: the policy's
weights and observation statistics; ``state.json``: the run's config and step) and
``card.json``, its model card: how it was trained (algorithm, config, seed, steps, wall clock,
drivelab commit, MetaDrive version, the command that reproduces it), its evaluation on
MetaDrive's protocol (the 200 unseen scenarios, start seeds 0-199: success, crash, out of road,
route completion and, on SafeMetaDrive, the episode cost, with 95% confidence intervals, per
episode too) beside MetaDrive's expert on the same scenarios, and the sha256 of each file.
``SHA256SUMS`` (the format of ``sha256sum``, so ``sha256sum -c SHA256SUMS`` checks it too) holds
the sha256 of every file, the card included: an edited card (a forged success rate) is refused
like a changed weight file.

Everything that takes a run or a checkpoint takes a shipped driver's name (``drivelab eval
drivelab-driver``, ``drivelab.load("drivelab-driver")``, ``drivelab export drivelab-driver``):
:func:`resolve_policy_path` turns the name into the directory, and any directory with a card is
checked against it first: a file whose hash differs is refused, as is an env whose observation
layout differs from the one the driver was trained on. A shipped driver without its card, or a
card without ``SHA256SUMS``, is refused rather than loaded unchecked.
"""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path

import gymnasium as gym
import numpy as np

from drivelab.errors import DrivelabError

DRIVERS_DIR = Path(__file__).resolve().parent.parent / "drivers"
CARD = "card.json"
SUMS = "SHA256SUMS"
# The files a driver consists of, each listed in SHA256SUMS: what loads (weights, config) and what vouches (card).
DRIVER_FILES = ("tensors.safetensors", "state.json", CARD)
# The metrics a card reports, in its order: MetaDrive's episode outcomes and how far the car got.
CARD_METRICS = ("success_rate", "crash_rate", "out_of_road_rate", "route_completion")
# ... and after them, when the evaluation has it: the mean episode cost (SafeMetaDrive, drivelab.envs.costs)
# and, with the episodes' lengths, the cost rate (total cost over total steps, as `drivelab eval`'s).
COST_CARD_METRICS = ("cost", "cost_rate")


def shipped_drivers() -> list[str]:
    """Names of the drivers inside the package (every directory, with its card or without:
    one that lost its card is refused when it is used, not mistaken for a missing name)."""
    found = DRIVERS_DIR.iterdir() if DRIVERS_DIR.is_dir() else []
    return sorted(p.name for p in found if p.is_dir() and not p.name.startswith((".", "_")))


def file_sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def read_sums(directory: Path) -> dict[str, str]:
    """``SHA256SUMS``: file name -> sha256, from lines ``<sha256>  <name>`` as ``sha256sum`` writes them."""
    if not (directory / SUMS).is_file():
        raise DrivelabError(f"driver {directory}: no {SUMS} (the sha256 of its files and model card), so it cannot "
                            "be checked; reinstall drivelab or download the driver again")
    try:
        lines = (directory / SUMS).read_text().splitlines()
    except (OSError, ValueError) as exc:
        raise DrivelabError(f"driver {directory}: {SUMS} cannot be read ({type(exc).__name__})") from None
    sums = {}
    for line in lines:
        match = re.fullmatch(r"([0-9a-f]{64}) [ *](.+)", line)  # "*": sha256sum's binary mode
        if match is None:
            raise DrivelabError(f"driver {directory}: {SUMS} has a line that is not '<sha256>  <file>': {line[:80]!r}")
        sums[match[2]] = match[1]
    return sums


def check_file(directory: Path, name: str, sums: dict[str, str]) -> None:
    """One file of a driver is listed in ``SHA256SUMS``, exists and has that sha256."""
    if name not in sums:
        raise DrivelabError(f"driver {directory}: file {name} is not listed in its {SUMS}")
    if not (directory / name).is_file():
        raise DrivelabError(f"driver {directory}: file {name} named by its {SUMS} is missing")
    if file_sha256(directory / name) != sums[name]:
        raise DrivelabError(f"driver {directory}: file {name} does not match the sha256 in its {SUMS} "
                            "(changed or corrupted; reinstall drivelab or download the driver again)")


def write_sums(directory: Path) -> Path:
    """Write ``SHA256SUMS`` for the files of the driver in ``directory`` (after its card)."""
    lines = [f"{file_sha256(directory / name)}  {name}\n" for name in DRIVER_FILES]
    (directory / SUMS).write_text("".join(lines))
    return directory / SUMS


def read_card(directory: Path) -> dict:
    """The model card of a driver, checked against ``SHA256SUMS`` before anything in it is read."""
    check_file(directory, CARD, read_sums(directory))
    try:
        card = json.loads((directory / CARD).read_text())
    except (OSError, ValueError) as exc:
        raise DrivelabError(f"model card {directory / CARD} cannot be read: {exc}") from None
    if not isinstance(card, dict) or not isinstance(card.get("files"), dict):
        raise DrivelabError(f"model card {directory / CARD} has no 'files' table of sha256 hashes")
    return card


def verify_files(directory: Path, card: dict) -> None:
    """Every file the card lists exists and has the card's sha256 (one line otherwise)."""
    for name, expected in card["files"].items():
        path = directory / name
        if not path.is_file():
            raise DrivelabError(f"driver {directory}: file {name} named by its model card is missing")
        if file_sha256(path) != expected:
            raise DrivelabError(f"driver {directory}: file {name} does not match the sha256 in its model card "
                                "(changed or corrupted; reinstall drivelab or download the driver again)")


def resolve_policy_path(path: str | Path) -> Path:
    """A shipped driver's name -> its directory; any other path unchanged. A driver directory
    (one with a model card or ``SHA256SUMS``) is verified before anything loads it: every file
    against ``SHA256SUMS``, card included, then the weights against the card. A shipped driver
    must have both: without them nothing would vouch for its files."""
    candidate = Path(path)
    if not candidate.exists() and str(path) in shipped_drivers():
        candidate = DRIVERS_DIR / str(path)
    shipped = candidate.is_dir() and candidate.resolve().parent == DRIVERS_DIR
    if shipped and not (candidate / CARD).is_file():
        raise DrivelabError(f"shipped driver {candidate.name} has no model card ({candidate / CARD}): its files cannot "
                            "be checked; reinstall drivelab")
    if (candidate / CARD).is_file() or (candidate / SUMS).is_file():
        sums = read_sums(candidate)
        for name in DRIVER_FILES:
            check_file(candidate, name, sums)
        verify_files(candidate, read_card(candidate))
    return candidate


def check_observation_layout(directory: Path, observation_space: gym.Space) -> None:
    """Refuse an env whose observations are not laid out as the driver's were in training."""
    if not (directory / CARD).is_file():
        return
    card = read_card(directory)
    trained = tuple(card.get("observation_shape") or ())
    if trained and trained != tuple(observation_space.shape):
        raise DrivelabError(f"driver {card.get('name', directory)} was trained on observations of shape {trained} "
                            f"({card.get('observation', 'see its card')}), this env gives {tuple(observation_space.shape)}: "
                            "evaluate it on an env with the same observation layout")


def format_card(card: dict) -> str:
    """The model card as text (``drivelab eval NAME --card``, ``drivelab models``)."""
    train = card.get("training", {})
    lines = [f"{card.get('name')}: {card.get('summary', '')}",
             f"  algorithm   {train.get('algo')} (config {train.get('config')}), seed {train.get('seed')}",
             f"  training    checkpoint at {train.get('steps'):,} env steps of a run of "
             f"{train.get('steps_trained', train.get('steps')):,} steps, {train.get('minutes')} min on {train.get('machine')}",
             f"  software    drivelab {train.get('drivelab_commit')}, metadrive-simulator {train.get('metadrive_version')}",
             f"  reproduce   {train.get('reproduce')}",
             f"  observation {card.get('observation')} {tuple(card.get('observation_shape', ()))}"]
    evaluation = card.get("evaluation", {})
    if evaluation:
        policies = evaluation.get("policies", {})
        # the cost column when some policy has it; a policy without a metric shows "-" in its cell
        metrics = CARD_METRICS + tuple(m for m in COST_CARD_METRICS
                                       if any(m in result for result in policies.values()))
        lines.append(f"  evaluation  {evaluation.get('protocol')}")
        header = "    {:<22}" + "{:>22}" * len(metrics)
        lines.append(header.format("policy", *metrics) + "    (mean ± 95% CI of the mean)")
        for who, result in policies.items():
            lines.append(header.format(who, *(_cell(result, m) for m in metrics)))
    return "\n".join(lines)


def _cell(result: dict, metric: str) -> str:
    """A card's cell: mean ± 95% CI (a cost per step, ~0.01, to 4 digits), or "-" when the policy lacks it."""
    if metric not in result:
        return "-"
    digits = 4 if metric == "cost_rate" else 3
    return f"{result[metric]['mean']:.{digits}f} ± {result[metric]['ci95']:.{digits}f}"


def model_card(path: str | Path) -> str:
    """The model card of a driver (a shipped name or a directory), verified and formatted."""
    directory = resolve_policy_path(path)
    if not (directory / CARD).is_file():
        raise DrivelabError(f"{path} has no model card ({CARD}); drivelab models lists the shipped drivers")
    return format_card(read_card(directory))


def card_metrics(per_episode: dict[str, list[float]]) -> dict[str, dict[str, float]]:
    """{metric: {mean, ci95}} of per-episode outcomes (95% CI of the mean, Student's t): the card's
    metrics that ``per_episode`` holds, the episode cost included when it does, and the cost rate
    when it has the episodes' ``length`` too."""
    from drivelab.training.outputs.statistics import mean_and_ci95

    out = {}
    for name in CARD_METRICS + COST_CARD_METRICS:
        if name in per_episode:
            mean, half = mean_and_ci95(np.asarray(per_episode[name], float))
            out[name] = {"mean": round(float(mean), 4), "ci95": round(float(half), 4)}
    if "cost" in per_episode and "length" in per_episode:
        cost, length = np.asarray(per_episode["cost"], float), np.asarray(per_episode["length"], float)
        rate = cost.sum() / length.sum()
        # a ratio of two sums: its CI by the delta method, the CI of the mean of cost - rate x length
        # over the mean length (Cochran, Sampling Techniques, 1977, eq. 6.13)
        _, half = mean_and_ci95(cost - rate * length)
        out["cost_rate"] = {"mean": round(float(rate), 6), "ci95": round(float(half / length.mean()), 6)}
    return out


def write_driver(out: Path, policy_dir: Path, card: dict) -> Path:
    """Write a driver directory: the policy files in ``policy_dir`` (as ``TrainedPolicy.save``
    wrote them) and ``card`` with their sha256 added as ``files``."""
    out.mkdir(parents=True, exist_ok=True)
    files = {}
    for name in ("tensors.safetensors", "state.json"):
        (out / name).write_bytes((policy_dir / name).read_bytes())
        files[name] = file_sha256(out / name)
    (out / CARD).write_text(json.dumps({**card, "files": files}, indent=1) + "\n")
    write_sums(out)  # last: the card's own hash too
    return out
