"""The untrusted-code boundary: the policy process and what crosses into and out of it.

``workers`` starts the two zygotes (policy processes; game hosts) and runs tasks in their workers, an episode as
a host joined to a policy process (the parent's side); ``zygote`` forks one worker per task (``preload`` warms
it, and keeps the emulator out of the policy zygote); ``confine`` is the kernel's confinement of a policy
process (rlimits, capabilities, then ``landlock`` and ``seccomp``), with what the zygote sets up beforehand:
``namespaces`` (pid, IPC, network; lifetimes) and ``mounts`` (the minimal filesystem view, scratch tmpfs), all
through ``libc``; ``view`` says which files a policy process may read; ``policy`` is the policy process's
side of an episode (observations in, actions out); ``wire`` is the frame format and the checks of every message a
worker sends; ``untrusted`` caps and scrubs text that came out of policy code. Nothing here knows how a game is
played: the host's side of an episode and the candidate checks live in ``pipeline/play`` and are named to the
zygotes by module path.
"""
