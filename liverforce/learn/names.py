"""Names of the learning stage's choices, in a module without imports (no torch).

:mod:`liverforce.config` validates ``model.encoder``, ``model.roi_features``,
``model.occlusion.mode``, ``model.force_scaling``, ``model.gp.kernel`` and the ``study`` lists against these, and the
implementations dispatch on them (:mod:`liverforce.learn.encoders`,
:mod:`liverforce.learn.representation`), so a name added here is valid in
the config and must be implemented there. Keep this module import-free: the
config loads it without importing the ``liverforce.learn`` package (which
imports torch).
"""

#: ROI feature encoders (liverforce.learn.encoders, fitted by liverforce.learn.model.fit_preprocessor)
ENCODERS = ("pca", "ae", "dae")

#: ROI features -> grid channels per point (liverforce.learn.representation.Representation)
ROI_FEATURE_CHANNELS = {"displacement": 3, "deformed": 1, "both": 4, "cloud": 2}
#: ROI features that need no node correspondence: a camera cloud and the tool tip (liverforce.learn.camera)
CAMERA_FEATURES = ("cloud",)

#: how the tool's occlusion hides ROI points (liverforce.learn.representation.Representation)
OCCLUSION_MODES = ("remove", "noise")

#: how a state-vector model brings in the material (liverforce.learn.model.fit_preprocessor)
FORCE_SCALINGS = ("linear", "stiffness", "none")

#: the GP regressor's stationary kernel, model.gp.kernel (liverforce.learn.gp)
GP_KERNELS = ("rational_quadratic", "squared_exponential")


def roi_features() -> tuple[str, ...]:
    """Names accepted as ``model.roi_features``."""
    return tuple(ROI_FEATURE_CHANNELS)


def gp_code_members(members) -> tuple[int, ...]:
    """``model.gp.code_members`` checked and sorted: PCA code sizes, each at least 1 and listed once (``()`` for
    none); a ValueError names what is wrong. The config validates with it and the learning stage reads with it."""
    members = tuple(int(k) for k in (members or ()))
    if any(k < 1 for k in members) or len(set(members)) != len(members):
        raise ValueError(f"PCA code sizes, each at least 1 and listed once; got {list(members)}")
    return tuple(sorted(members))
