"""The reduced robot's step in JAX, batched over robots on a CPU or an accelerator.

:mod:`~softcrawl.jaxsim.contact` holds the constraint solve (attachments and frictional floor
contact) of one robot with fixed, padded shapes, to be ``jax.vmap``-ped over a batch.
"""
