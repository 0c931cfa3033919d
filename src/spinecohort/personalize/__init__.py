"""Patient-personalized models: SSM mode weights whose model matches a patient's spinopelvic parameters.

Two ways to personalize (docs/explanation/ssm.md, "Personalized models"):

* **fit** (parameter-based, the seed's Figure 8 pipeline): find continuous weights ``b`` (SD units,
  within ``±bound_sd``) minimising the weighted parameter misfit
  ``sum_p (omega_p (f_p(b) - t_p))^2 + prior^2 |b|^2`` where ``f`` is the real measurement
  (``measure.measure``) of the SSM shape ``mean + sum_i sqrt(d_i) phi_i b_i``.  A quadratic surrogate of ``f``,
  fitted once to a quasi-random batch of sampled models, gives the start; bounded trust-region least squares
  (``scipy.optimize.least_squares``, ``trf``) on the real measurement refines it, with a central-difference
  Jacobian evaluated as one batch of ``2k + 1`` models.  The small ``prior`` term picks, among weight vectors
  that match the parameters equally well, the one closest to the mean (the most probable under the SSM's
  Gaussian): a handful of parameters does not determine ``k`` weights.
* **projection** (image-based): least-squares projection of the patient's own GPA-aligned shape on the first
  ``k`` modes, clipped to ``±bound_sd``.  Needs the patient's 3-D shape; matches the shape, not the parameters.

PI = PT + SS holds identically for every measured model, so a set of targets that gives all three must
satisfy it too.  Millimetres and degrees throughout.

- `parameters`: the parameters a target may name, the pelvic identity, and the measured parameters as a
  function of the weights (and posture), on the landmark vertices only.
- `fit`: the quadratic surrogate, the fit to targets, the projection of a shape.
- `cohort`: both methods for every patient, and a personalized model's checked hex coordinates.
- `report`: the error summary and the Markdown report.
"""
