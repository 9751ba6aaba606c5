"""Experiment: any model settings of one variant, chosen on training livers only.

For each setting (comma-separated ``dotted.key=value`` model overrides, values
read as YAML; ``default`` is the variant as configured) on a finished run's
shards (``--results``), through the pipeline's own
:func:`liverforce.learn.train.train_scenario` with the pipeline's seeds:

- **training-side CV MAE**: the 4-fold CV by liver inside the training livers
  (``cv_mae_n``) on ``--cv-splits`` seeded splits (the main split, then those of
  ``train.repeats``), each split trained as its own run. A default is chosen on
  this alone: no test or unseen liver enters it.
- **test accuracy** over the pipeline's ``train.repeats`` seeded splits, per split;
- for IV, **the unseen livers' MAE** (mean +- sd over livers; the saved model, the one
  the validation scores: with ``train.final_fit``, refitted on every IV case); with
  ``--observe`` (camera variants), also that of the same model re-observed with other
  observation settings, nothing refitted (``noise_sd_mm=1.0``: a noisier camera).

::

    PYTHONPATH=. OMP_NUM_THREADS=1 .venv/bin/python benchmarks/experiment_settings.py --results results/default \\
        --variant cloud_sv --settings default force_scaling=linear "force_scaling=linear,gp.kernel=rational_quadratic"
"""

from __future__ import annotations

import argparse

import yaml


def parse_setting(text: str, variant: dict) -> dict:
    """``a.b=1,c=x`` -> ``{"a": {"b": 1}, "c": "x"}``, refused (SystemExit) unless every key is a model setting
    and the variant with these overrides passes the config's model checks."""
    from liverforce.config import ConfigError, _check_model, _unknown_keys, merge_mapping

    over: dict = {}
    if text == "default":
        return over
    for key, value in _items(text, "--settings"):
        parts = key.split(".")
        node = over
        for p in parts[:-1]:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise SystemExit(f"--settings: '{key}' sets a key inside a value")
        node[parts[-1]] = value
    unknown = _unknown_keys(variant, over)
    if unknown:
        raise SystemExit(f"--settings '{text}': not model settings: {unknown}")
    _same_shape(variant, over, text, "model.")
    try:
        _check_model(merge_mapping(variant, over), f"--settings {text}")
    except ConfigError as exc:
        raise SystemExit(str(exc)) from exc
    return over


def _same_shape(base: dict, over: dict, text: str, prefix: str) -> None:
    """Refuse a value where the config has a group (``camera=1``) or a group where it has a value."""
    for k, val in over.items():
        if isinstance(base[k], dict) != isinstance(val, dict):
            kind = "a group of settings" if isinstance(base[k], dict) else "a single value"
            raise SystemExit(f"--settings '{text}': {prefix}{k} is {kind}")
        if isinstance(val, dict):
            _same_shape(base[k], val, text, f"{prefix}{k}.")


def _items(text: str, flag: str):
    """``(key, value)`` of each ``key=value`` of ``text`` (:func:`_split_top`; values read as YAML), refused
    (SystemExit, naming ``flag``) where an item is not ``key=value``."""
    for item in _split_top(text):
        key, sep, value = item.partition("=")
        if not sep:
            raise SystemExit(f"{flag}: '{item}' is not key=value")
        yield key.strip(), yaml.safe_load(value)


def _split_top(text: str) -> list[str]:
    """``text`` split at the commas outside brackets (a value may be a YAML list: ``n_points=[500, 900]``)."""
    items, depth, cur = [], 0, ""
    for ch in text:
        depth += (ch in "[{") - (ch in "]}")
        if ch == "," and depth == 0:
            items.append(cur)
            cur = ""
        else:
            cur += ch
    return items + [cur]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default="results/default")
    ap.add_argument("--variant", default="pca_sv")
    ap.add_argument("--scenario", default="IV")
    ap.add_argument("--settings", nargs="+", default=["default"])
    ap.add_argument("--cv-splits", type=int, default=5, help="seeded splits the training-side CV MAE is averaged over")
    ap.add_argument("--observe", nargs="*", default=[],
                    help="camera variants, IV: the unseen livers also re-observed with each of these observation "
                         "settings (key=value[,key=value], values as YAML), nothing refitted")
    ap.add_argument("--out", default="/tmp/liverforce-experiment-settings")
    args = ap.parse_args()

    from liverforce.config import merge_mapping

    from benchmarks.experiment import PipelineTraining

    run = PipelineTraining(args.results, "settings experiment")
    v = dict(run.variants[args.variant])
    overs = [(text, parse_setting(text, v)) for text in args.settings]  # all checked before any training
    observe = [(text, parse_observation(text)) for text in args.observe]
    if observe and (args.scenario != "IV" or v.get("roi_features") != "cloud"):
        raise SystemExit("--observe re-observes a camera variant's saved model on the unseen livers: scenario IV and "
                         f"a camera variant only (got {args.variant}, {args.scenario})")
    for k, (text, over) in enumerate(overs):
        print(run.score(merge_mapping(v, over), args.scenario, args.variant, text,
                        f"{args.out}/{args.variant}-{args.scenario}-{k}", args.cv_splits, observe), flush=True)


def parse_observation(text: str) -> dict:
    """``noise_sd_mm=1.0,n_points=[5000, 5000]`` -> observation settings, refused (SystemExit) unless valid."""
    from liverforce.learn.observation import ObservationConfig

    out = dict(_items(text, "--observe"))
    try:
        ObservationConfig.from_dict(out)
    except (TypeError, ValueError) as exc:
        raise SystemExit(f"--observe '{text}': {exc}") from exc
    return out


if __name__ == "__main__":
    main()
