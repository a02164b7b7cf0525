"""LLM access: every model call goes through here.

``client`` is the litellm client (and the replay client that answers from stored replies); ``providers`` says
what each provider accepts, its key and its price; ``local`` runs the offline SmolLM2 server; ``tokens`` counts
tokens the way the model does.
"""
