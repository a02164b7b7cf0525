"""Many optimization runs at once: ``batch`` reads an experiment file and runs it in local processes or on Ray;
``worker`` is one run of a batch (its own process, or a Ray task).
"""
