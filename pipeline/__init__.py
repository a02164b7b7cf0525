"""The pipeline: everything that plays, learns and is driven from the command line, in sub-packages along the
data path (docs/architecture.md draws it):

- ``settings``  how a setting is declared once (its flag, help, checks, batch key, ``--resume`` rule) and the
                episode limits every layer above plays under (a module below the sub-packages);
- ``boundary``  the policy process and what crosses into and out of it: confinement, the zygotes, workers, the
                wire format, untrusted text;
- ``play``      the trusted side of playing: the game host (environment and score where no policy code runs),
                episodes, candidate checks, evaluation, the replay check, playing two versions side by side;
- ``llm``       LLM access: the client, what each provider accepts, the offline model, token counts;
- ``optimizer`` the loop: settings, strategies, proposals, assessment, the prompt and its context, feedback;
- ``jobs``      many runs at once: batch files, local processes and Ray;
- ``cli``       the ``codearcade`` command: one module per verb.

The rule of direction: a sub-package imports only those listed before it (``play`` and ``llm`` side by side,
neither importing the other), and the pipeline imports games, tracing, store and viewers, never the reverse.
``tests/test_architecture.py`` checks it over every import.
"""
