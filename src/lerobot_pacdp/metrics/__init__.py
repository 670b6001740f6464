"""Generalization metrics of PAC-DP and diffusion-policy checkpoints (paper Sec. IV).

- `noise_prediction`: held-out noise-prediction error (NPE) with paired, seeded draws, errors clustered by
  episode; `comparison`: the paired difference of two checkpoints' NPE.
- `nll_bound`: Kong et al. (2023)'s variational NLL bound (nats and bits per action dimension), and the
  paper-compatible estimate (not a bound).
- `certificate`: PAC-Bayes risk certificate (`pacdp-certify`); `learned_prior`: data-dependent prior
  from a disjoint split (`pacdp-learned-prior`); `kl_inverse`: kl^-1.
- `sweep`: every checkpoint of lerobot-train runs -> CSV/JSON, Fig. 3-style plots, summary (`pacdp-metrics`).

Kept empty of imports: `import lerobot_pacdp.metrics.<module>` loads only what it needs.
"""
