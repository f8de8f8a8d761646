"""Training: the trainer built once from config (:mod:`.trainer`), posediff's callbacks
(:mod:`.callbacks`), atomic checkpoint writes (:mod:`.checkpoint_io`) and few-step distillation
(:mod:`.distill`)."""
