"""Encoders: PCA exactness, and the denoising autoencoder learns occluded -> clean."""

import numpy as np

from liverforce.learn.encoders import PCAEncoder
from liverforce.learn.model import fit_preprocessor, prepare
from liverforce.learn.representation import Representation
from liverforce.learn.synthetic import synthetic_arrays


def test_pca_reconstructs_rank_k_data_exactly():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(50, 3)) @ rng.normal(size=(3, 40)) + 2.0
    pca = PCAEncoder.fit(x, 3)
    np.testing.assert_allclose(pca.decode(pca.encode(x)), x, atol=1e-10)
    again = PCAEncoder.fit(x, 3)  # deterministic signs
    np.testing.assert_array_equal(again.components, pca.components)


def test_dae_restores_the_occluded_centre_better_than_an_ae():
    arrays = synthetic_arrays(160, seed=6, nodes=(200, 300), dent_width_mm=8.0)
    rep = Representation(grid_size=8, half_width_mm=14.0, occlusion_radius_mm=6.0, occlusion_mode="remove")
    prep = prepare(arrays, rep, observation_seeds=[0])
    kw = dict(rep=rep, code_size=3, use_state=False, seed=0, epochs=120, lr=3e-3, batch_size=32)
    errors = {}
    for kind in ("ae", "dae"):
        pre = fit_preprocessor(prep, encoder=kind, dae_input_noise=0.0, **kw)
        fs = pre.feature_scaler
        rec = pre.encoder.decode(pre.encoder.encode(fs.transform(prep.x_obs[0])))
        errors[kind] = float(np.mean((rec - fs.transform(prep.x_clean)) ** 2))
    # the AE reproduces what it sees (the flattened, occluded dent); the DAE learned the clean target
    assert errors["dae"] < 0.5 * errors["ae"], errors
