"""The trusted side of playing: the game host, episodes, candidate checks, evaluation, the replay check.

``rollout`` plays one episode as the game host (the environment and the score here, the policy behind a
channel: a confined policy process, or this process with ``--workers 0``); ``episodes`` is the episode task on
both sides (the host's, and the parent's check of what a host sends, field by field) and plays many;
``verify`` builds the row the parent stores and re-checks a stored run by replay (``doctor --replay``);
``validate`` checks a policy file or a candidate (static checks and a run on recorded observations, in policy
processes); ``evaluate`` is ``codearcade eval``; ``versus`` plays two versions on the same seeds and finds where
they part; ``runinfo`` and ``versions`` make run, episode and policy-version ids and rows.
"""
