"""Cache section of the experiment config: Dynamic Latent Bootstrapping (owned by sword_jax.dlb)."""

from __future__ import annotations

import dataclasses

WRITE_SOURCES = ("one_step", "sampler")


@dataclasses.dataclass(frozen=True)
class CacheConfig:
    """Dynamic Latent Bootstrapping cache: read schedule and write-back rule.

    Defaults are the paper's best design: linear schedule, direct replacement, write all chunks.
    The read probability ends at 1 (``read_prob_end``): the paper's Section 3 gives no cap and says
    "we gradually increase the probability of replacing ground-truth historical latents with cached
    predictions" and "This dynamic bootstrapping process enables a smooth transition from
    ground-truth conditioning to prediction-based conditioning." (Until this field's default
    changed it stopped at 0.5; set ``--cache.read_prob_end=0.5`` for the old behaviour.)

    Attributes:
      enabled: False = plain teacher forcing (no cache in the train state).
      schedule: how ``read_prob`` (probability of reading the context from the cache, i.e.
        1 - teacher-forcing share) moves from ``read_prob_start`` to ``read_prob_end``:
        ``linear`` over ``schedule_steps`` steps from step 0 (``warmup_steps`` ignored), or
        ``warmup_cosine``: held at the start value for ``warmup_steps``, then a cosine half-wave
        to the end value over ``schedule_steps``. See :func:`sword_jax.dlb.schedule.read_prob`.
      replacement: ``direct`` (slot := prediction) or ``ema`` (slot := (1 - ema_rate) * slot +
        ema_rate * prediction; an empty slot takes the prediction).
      ema_rate: weight of the new prediction in ``ema`` replacement.
      scope: write the first predicted latent of each sample only (``single``) or all (``all``).
      write_source: what is written into the cache for the future latents of each sample.
        ``one_step``: the clean-latent estimate implied by the training forward pass at the sampled
        noise level (free, but at sigma ~0.8 a blurred conditional mean, not what inference makes).
        ``sampler``: the model's own flow sampler (:func:`sword_jax.world_model.sampler.sample`,
        current params, no gradient, ``flow.guidance_scale``) run from fresh noise on the same
        conditioning for ``write_sample_steps`` Euler steps: what inference would put in the
        context, at ``write_sample_steps`` extra forward passes per step (x2 with guidance).
      write_sample_steps: Euler steps of the ``sampler`` source; None = ``flow.sample_steps`` (the
        inference setting).
      log_inference_distance: on log steps (``trainer.log_every``, and the last step), sample the
        inference context for the written latents (``flow.sample_steps`` steps, fresh noise) and
        report ``cache_vs_inference_*`` metrics (:mod:`sword_jax.world_model.cache_fidelity`); other steps skip
        it (``lax.cond``) and report NaN.
      dtype: storage dtype of the cache (bfloat16 keeps the paper's dataset under 5 GB).
    """

    enabled: bool = True
    schedule: str = "linear"  # linear | warmup_cosine
    read_prob_start: float = 0.0
    read_prob_end: float = 1.0
    schedule_steps: int = 100
    warmup_steps: int = 10
    replacement: str = "direct"  # direct | ema
    ema_rate: float = 0.5
    scope: str = "all"  # single | all
    write_source: str = "one_step"  # one_step | sampler
    write_sample_steps: int | None = None
    log_inference_distance: bool = True
    dtype: str = "bfloat16"  # bfloat16 | float32

    def validate(self) -> None:
        if self.schedule not in ("linear", "warmup_cosine"):
            raise ValueError(f"cache.schedule must be linear|warmup_cosine, got {self.schedule!r}")
        if self.replacement not in ("direct", "ema"):
            raise ValueError(f"cache.replacement must be direct|ema, got {self.replacement!r}")
        if self.scope not in ("single", "all"):
            raise ValueError(f"cache.scope must be single|all, got {self.scope!r}")
        if self.write_source not in WRITE_SOURCES:
            raise ValueError(f"cache.write_source must be one_step|sampler, got {self.write_source!r}")
        if self.write_sample_steps is not None and not 1 <= self.write_sample_steps <= 50:
            raise ValueError(f"cache.write_sample_steps must be in [1, 50], got {self.write_sample_steps}")
        if self.dtype not in ("bfloat16", "float32"):
            raise ValueError(f"cache.dtype must be bfloat16|float32, got {self.dtype!r}")
        if self.schedule_steps <= 0 or self.warmup_steps < 0:
            raise ValueError(
                f"cache.schedule_steps must be > 0 and warmup_steps >= 0, got {self.schedule_steps}/{self.warmup_steps}"
            )
        for name in ("read_prob_start", "read_prob_end", "ema_rate"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"cache.{name} must be in [0, 1], got {value}")
