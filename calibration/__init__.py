"""Pure numerics: decoding, camera models, fitting, evaluation; no hardware, no HTTP."""
