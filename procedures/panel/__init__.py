"""The operator panel: the shop-floor run in a browser (live state, prompts, pause/abort, history)."""
