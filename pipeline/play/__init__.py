"""The trusted side of what runs in policy workers: episodes, candidate checks, evaluation, score verification.

``rollout`` plays one episode (in a worker); ``episodes`` is the episode task on both sides of the boundary
(what a worker sends, checked field by field) and plays many; ``verify`` recomputes every score by replay;
``validate`` checks a policy file or a candidate (static checks and a run on recorded observations, in
workers); ``evaluate`` is ``codearcade eval``; ``versus`` plays two versions on the same seeds and finds where
they part; ``runinfo`` and ``versions`` make run, episode and policy-version ids and rows.
"""
