"""Few-shot exploration (paper §3.3): its settings (``config``), the candidate proposals
(``proposals``), the selection rules (``selection``) and their registry (``strategies``), the
geometric familiarity (``familiarity``), fine-tuning after each round (``finetune``), the loop
(``explore``), its session log on disk (``session_log``) and the evaluation of the adapted
model (``evaluate``). The top of the core: stands on every other part of it."""
