"""The untrusted-code boundary: the policy process and what crosses into and out of it.

``workers`` starts the zygote and runs tasks in confined workers (the parent's side); ``zygote`` forks one
worker per task (``preload`` warms it); ``confine`` is the kernel's confinement of a worker; ``wire`` is the
frame format and the checks of every message a worker sends; ``untrusted`` caps and scrubs text that came
out of policy code. Nothing here knows what a task does: the tasks (episodes, candidate checks) live in
``pipeline/play`` and are named to the zygote by module path.
"""
