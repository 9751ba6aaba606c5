"""Every seed of the package comes from here: one derivation, named by stage and keys.

A stochastic step never does arithmetic on a seed (``seed * 7919 + i``,
``seed + k``, ``[seed, 31]``): it asks :func:`derive` for the seed of its own
stage and keys. The workflow's seeds start from the config's master seed
``seed`` through :meth:`liverforce.pipeline.plan.Plan.seed`; a job derives the
seeds of its own sub-steps from the seed it was given, with :func:`derive` too.

Derivation
----------
``derive(seed, stage, *keys)`` is the first 32-bit word of
:class:`numpy.random.SeedSequence` over the entropy
``[seed, crc32(stage), crc32(str(key)) for each key]``, masked to 31 bits
(``0 <= value < 2**31``: valid for NumPy, SciPy's QMC samplers, torch, Ax and
gmsh alike). Properties:

- deterministic across processes, platforms and Python versions: CRC-32 of the
  UTF-8 text and NumPy's SeedSequence hashing (stable by NumPy's policy); no
  :func:`hash` (randomised per process for strings);
- different stages or keys give unrelated seeds (no ``seed + 1`` overlap
  between neighbouring streams); keys are compared as text, so ``3`` and
  ``"3"`` are the same key;
- the order of the keys matters.

Stages used by the package (``stage`` strings; keys in brackets)::

    mesh [gid]                 mesher seed of one geometry (Plan)
    mesh.exertion              the mesh stage's candidate exertion points (from the mesher seed)
    sweep [sweep.seed, scenario]  the case table of one scenario (Plan)
    sweep.exertion [gid]       fallback exertion points of a mesh without candidates (from the scenario seed)
    sweep.case [i]             the per-case seed stored in the shards (from the scenario seed)
    train [train.seed]         split seed of every training and study job of an experiment (Plan)
    split.test                 the held-out test split (from the split seed)
    split.cv                   the CV folds inside the training split (from the split seed)
    tune.fold [k]              fold k's regressor fit in cross-validation (from the split seed)
    gp.subset                  the training rows of a GP fit above model.gp.max_points (from the fit's seed)
    encoder.fold [k]           fold k's scalers and encoder in cross-validation (from the split seed)
    split.repeat [r]           the r-th repeated train/test split (r >= 1; from the split seed)
    split.calibration          the interval's calibration split inside the training split (from the split seed)
    split.study                a study point's validation split inside the training split (from the split seed)
    interval.fit               the calibration model's fit and observation draws (from the split seed)
    observation.view [v]       the v-th observed training view (from a split seed)
    observation.eval           the observation drawn to evaluate a test split (from a split seed)
    tune.ax                    the Ax client and its Sobol phase (from the split seed)
    torch.batches              the mini-batch order of one fit (from the fit's seed)
    study.train_size           the learning curve's per-liver subsets (from the split seed)
    study.train_livers         the order of the training livers in their learning curve (from the split seed)
    split.points               the exertion-point folds of the held-out-points evaluation (from the split seed)
    points.fit                 those folds' fits and observation draws (from the split seed)
    observation [case]         a case's occlusion and noise draw (from an observation seed)
    observation.camera [case]  a case's camera observation draw (from an observation seed)
    observation.tip [case]     a case's tool-tip (robot kinematics) noise draw (from an observation seed)
    validate.registration [case]  a case's misregistration directions in the validation (from the evaluation's
                               observation seed)
    validate.registration.unloaded  the unloaded views' observation seed of those rows (from the same)
    validate.shape [liver]     a liver's change of shape since its scan in the validation's shape rows (from the
                               evaluation's observation seed)

Helpers that also touch seeds live here, so no other module does:
:func:`spawn_rngs` (independent streams of one draw), :func:`liver_seeds`
(the seeds, i.e. identities, of a population of procedural livers),
:func:`liver_rng` (the procedural liver generator's streams) and
:func:`gmsh_random_seed` (gmsh's ``Mesh.RandomSeed`` convention).
"""

from __future__ import annotations

import zlib

import numpy as np

__all__ = ["derive", "spawn_rngs", "liver_rng", "liver_seeds", "gmsh_random_seed", "SEED_BITS"]

#: derived seeds are in ``[0, 2**SEED_BITS)``
SEED_BITS = 31


def _crc(text) -> int:
    return zlib.crc32(str(text).encode("utf-8"))


def derive(seed: int, stage: str, *keys) -> int:
    """The seed of ``stage`` (and ``keys``) derived from ``seed``.

    Parameters
    ----------
    seed : int
        A non-negative integer: the config's master seed, or a seed this
        function returned.
    stage : str
        What the seed is for, e.g. ``"sweep"`` or ``"split.test"`` (module docstring).
    *keys
        What distinguishes the draws within the stage (a geometry id, a
        scenario, a fold index ...); each is compared as ``str(key)``.

    Returns
    -------
    int
        A seed in ``[0, 2**31)``; the same arguments give the same seed in
        every process.

    Examples
    --------
    >>> derive(0, "sweep", 0, "I") == derive(0, "sweep", 0, "I")
    True
    >>> derive(0, "sweep", 0, "I") != derive(0, "sweep", 0, "II")
    True
    """
    if isinstance(seed, bool) or int(seed) != seed or int(seed) < 0:
        raise ValueError(f"seeds are non-negative integers (got {seed!r})")
    if not isinstance(stage, str) or not stage:
        raise ValueError(f"a seed's stage is a non-empty string (got {stage!r})")
    entropy = [int(seed), _crc(stage), *(_crc(k) for k in keys)]
    word = np.random.SeedSequence(entropy).generate_state(1, dtype=np.uint32)[0]
    return int(word) & ((1 << SEED_BITS) - 1)


def spawn_rngs(seed, n: int) -> list[np.random.Generator]:
    """``n`` independent generators of one draw: ``SeedSequence(seed).spawn(n)``.

    ``seed``: a non-negative integer (e.g. from :func:`derive`) or a sequence
    of them. Used where one seeded draw has several parts that
    must not share a stream (the camera observation: pose, sampling, noise).
    """
    entropy = [int(s) for s in np.atleast_1d(np.asarray(seed, dtype=object)).ravel()]
    if not entropy or any(s < 0 for s in entropy):
        raise ValueError(f"seeds are non-negative integers (got {seed!r})")
    return [np.random.default_rng(s) for s in np.random.SeedSequence(entropy).spawn(int(n))]


def liver_seeds(first: int, count: int) -> range:
    """The generator seeds of a population of procedural livers: ``first``, ``first + 1``, ...

    Not a derivation: a procedural liver's seed is its identity (its id is
    ``proc-<seed:04d>`` or ``val-<seed:04d>``, ``geometry.procedural.seed`` /
    ``validate.seed`` name the first one), so consecutive livers have
    consecutive seeds.
    """
    return range(int(first), int(first) + int(count))


#: fixed stream keys of the procedural liver generator (:mod:`liverforce.geometry.procedural`)
_LIVER_STREAMS = {"shape": 0x11FE5, "volume": 0x7015}


def liver_rng(seed: int, stream: str) -> np.random.Generator:
    """A random stream of the procedural liver generator for the liver of seed ``seed``.

    ``stream``: ``"shape"`` (the shape factors) or ``"volume"`` (the drawn
    volume). Kept as ``SeedSequence([seed, fixed key])`` rather than
    :func:`derive`: a liver's seed is its identity, and these streams define
    the shapes of every procedural liver the tests, benchmarks and README
    measure; changing them redraws every liver.
    """
    if stream not in _LIVER_STREAMS:
        raise ValueError(f"unknown liver stream '{stream}' (one of {', '.join(_LIVER_STREAMS)})")
    return np.random.default_rng(np.random.SeedSequence([int(seed), _LIVER_STREAMS[stream]]))


def gmsh_random_seed(seed: int) -> int:
    """gmsh's ``Mesh.RandomSeed`` for a mesher seed: ``seed + 1`` (gmsh's default, 1, for seed 0).

    Wrapped into gmsh's int range (``1 .. 2**31 - 1``): the derived seed ``2**31 - 1`` maps to 1 as seed 0 does.
    """
    return int(seed) % (2**31 - 1) + 1
