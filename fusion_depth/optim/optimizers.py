"""The ``optimizer`` group: ``torch.optim`` optimizers, configured by their own arguments
(``optimizer=adam``: :class:`torch.optim.Adam`). What their values may be is checked before
training, where torch would refuse them only inside the first step."""

from __future__ import annotations

from fusion_depth.utils.schema import NON_NEGATIVE, POSITIVE, Rule, Schema, is_number

# What the arguments the torch optimizers share accept (fusion_depth.utils.schema).
ARGUMENT_RULES: Schema = {
    "lr": Rule(POSITIVE.ok, "a learning rate > 0"),
    "betas": Rule(
        lambda v: (
            isinstance(v, list) and len(v) == 2 and all(is_number(b) and 0 <= b < 1 for b in v)
        ),
        "[beta1, beta2], each in [0, 1)",
    ),
    "eps": POSITIVE,
    "weight_decay": NON_NEGATIVE,
    "momentum": NON_NEGATIVE,
}
