"""Out-of-distribution (O.O.D.) gate: uncertainty scores, calibration and a one-sided likelihood-ratio test.

The paper's first safety layer. An ensemble of N diffusion policies predicts N action sequences; per
predicted step t the ensemble gives a covariance Sigma_t (A x A). A scalar uncertainty score summarises
the prediction, and a test against a model of in-distribution (I.D.) scores decides whether the current
state is O.O.D., in which case control is released to the surgeon.

======================  ==========================================================================
module                  what it holds
======================  ==========================================================================
``score``               the uncertainty scores of an ensemble covariance (sigma_hat, trace, logdet)
``calibration``         the I.D. score model and the test's threshold, fitted on I.D. scores
``likelihood_ratio``    the one-sided likelihood-ratio test (its derivation) and false-alarm rates
``gate``                the one gate: :class:`~lerobot_suture.safety.ood.gate.OODGate`, the latched test, and
                        :class:`~lerobot_suture.safety.ood.gate.ChunkGate`, a chunk detector feeding it
``calibration_file``    the ensemble's and STAC's calibration files in a pretrained policy directory
``chunk_consistency``   STAC: the chunk detector for any policy that predicts chunks
======================  ==========================================================================
"""
