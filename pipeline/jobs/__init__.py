"""Many optimization runs at once: ``experiments`` reads an experiment file into a batch of runs; ``batch`` runs
them in local processes or on Ray; ``worker`` is one run of a batch (its own process, or a Ray task).
"""
