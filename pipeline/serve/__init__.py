"""``codearcade serve``: a budgeted rollout server for one run, so that any coding agent (Claude Code, Codex CLI, a
script) can be the optimizer. ``config`` declares its settings, ``protocol`` is the protocol itself (the budget, the
training instances, submissions as policy versions, feedback, finalize on sealed pools), ``http`` and ``tools``
are its two transports (plain HTTP+JSON, and MCP with the official SDK). docs/serve.md says how to use it."""
