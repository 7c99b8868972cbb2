"""Autorank analysis of repeated detector scores (the paper's Tables IV-V and Figures 4-5).

``rank_detectors`` takes one list of paired samples per detector (sample k of every detector comes
from the same dataset and repeat seed) and runs ``autorank`` (Herbold 2020, after Demšar 2006):
the omnibus test (Friedman for non-parametric data), the Nemenyi critical difference, and per
detector the mean rank (1 = best, higher scores are better), median, median absolute deviation, the
confidence interval of the median and the effect size (Akinshin's gamma against the best-ranked
detector) with its magnitude. The paper reports the non-parametric form (MR, MED, MAD, CI, gamma,
Mag.), which is the default ``mode``; ``parametric`` and autorank's own choice (``auto``) are kept
for users who want them.
"""

from __future__ import annotations

import contextlib
import io
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from frontends.errors import ConfigError

StatsMode = Literal["nonparametric", "parametric", "auto"]


@dataclass(frozen=True)
class DetectorRank:
    name: str
    mean_rank: float
    #: Median (non-parametric) or mean (parametric) of the samples.
    centre: float
    #: Median absolute deviation (non-parametric) or standard deviation (parametric).
    spread: float
    ci_lower: float
    ci_upper: float
    #: Against the best detector (Akinshin's gamma, or Cohen's d if parametric); inf when both spreads are 0.
    effect_size: float
    magnitude: str


@dataclass(frozen=True)
class RankAnalysis:
    metric: str
    samples: int
    omnibus: str
    p_value: float
    #: The critical difference of the mean ranks (Nemenyi); None for parametric post-hoc tests.
    critical_difference: float | None
    #: Best first.
    ranks: tuple[DetectorRank, ...]
    #: autorank's result, for the CD diagram.
    result: object

    def markdown(self) -> str:
        parametric = self.omnibus in ("anova", "ttest")
        centre, spread = ("mean", "std") if parametric else ("MED", "MAD")
        lines = [
            f"| {self.metric} | MR | {centre} | {spread} | CI | γ | Mag. |",
            "|---|---|---|---|---|---|---|",
        ]
        for r in self.ranks:
            lines.append(
                f"| {r.name} | {r.mean_rank:.2f} | {r.centre:.3f} | {r.spread:.3f} | "
                f"[{r.ci_lower:.3f}, {r.ci_upper:.3f}] | {effect(r.effect_size)} | {r.magnitude} |"
            )
        cd = f", CD {self.critical_difference:.2f}" if self.critical_difference is not None else ""
        lines.append("")
        lines.append(f"{self.samples} paired samples; {self.omnibus} p = {self.p_value:.3g}{cd}")
        return "\n".join(lines)


def effect(value: float) -> str:
    """An effect size for a table: "-" when undefined, "inf" when a spread of zero makes it infinite."""
    if np.isnan(value):
        return "-"
    return f"{value:.2f}" if np.isfinite(value) else ("-inf" if value < 0 else "inf")


def rank_detectors(
    samples: Mapping[str, Sequence[float]],
    metric: str,
    alpha: float = 0.05,
    mode: StatsMode = "nonparametric",
) -> RankAnalysis:
    """Autorank over paired ``samples`` (detector -> one value per sample; higher is better)."""
    import pandas as pd
    from autorank import autorank

    lengths = {len(values) for values in samples.values()}
    if len(samples) < 2 or len(lengths) != 1:
        raise ConfigError(f"autorank {metric}: need >= 2 detectors with the same number of samples")
    count = lengths.pop()
    if count < 5:
        raise ConfigError(f"autorank {metric}: {count} paired samples; autorank needs at least 5")
    # autorank's ``order="descending"`` ranks correctly but lists the worst detector first and takes
    # effect sizes against it; the negated scores in ascending order list the best first and give
    # effect sizes against the best, as the paper's tables do. Values are negated back below.
    negated = pd.DataFrame({name: -np.asarray(values, dtype=np.float64) for name, values in samples.items()})
    with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()):
        # Constant columns (deterministic detectors) make the normality and effect-size helpers warn;
        # autorank prints its table even when not verbose.
        warnings.simplefilter("ignore")
        result = autorank(
            negated,
            alpha=alpha,
            verbose=False,
            order="ascending",
            force_mode=None if mode == "auto" else mode,
            random_state=0,
        )
    frame = result.rankdf
    parametric = "mean" in frame.columns and "median" not in frame.columns
    centre, spread = ("mean", "std") if parametric else ("median", "mad")
    ranks = tuple(
        DetectorRank(
            str(name),
            float(row["meanrank"]),
            -float(row[centre]),
            float(row[spread]),
            -float(row["ci_upper"]),
            -float(row["ci_lower"]),
            -float(row["effect_size"]),
            str(row["magnitude"]),
        )
        for name, row in frame.iterrows()
    )
    cd = getattr(result, "cd", None)
    return RankAnalysis(
        metric,
        count,
        str(result.omnibus),
        float(result.pvalue),
        float(cd) if cd is not None else None,
        ranks,
        result,
    )


def plot_critical_difference(analysis: RankAnalysis, path: Path) -> bool:
    """The critical-difference diagram (autorank's ``plot_stats``); False when autorank cannot draw it
    (a parametric post-hoc test, or no significant difference), in which case nothing is written."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from autorank import plot_stats

    if analysis.critical_difference is None:
        return False
    with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()):
        warnings.simplefilter("ignore")
        ax = plot_stats(analysis.result, allow_insignificant=True)
    if ax is None:
        return False
    figure = ax.get_figure()
    figure.suptitle(f"critical difference: {analysis.metric}", y=1.12)
    figure.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(figure)
    return True
