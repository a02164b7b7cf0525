"""The optimization loop: from a run's history in the store to the next policy versions, and back.

``loop`` drives the iterations; ``config`` holds the run's settings and their checks; ``state`` what the loop
carries between iterations; ``strategies`` decide what to improve; ``propose`` turns a request into a checked
candidate (``context`` reads what the prompt shows from the store, ``prompt`` renders it under the token
budget, ``reply`` parses the answer); ``assess`` plays the candidates; ``feedback`` and ``task`` are the staged
feedback and the game's task settings; ``estimate`` prices a run before it starts; ``replay`` re-runs one from
stored replies; ``runs`` compares two runs.
"""
