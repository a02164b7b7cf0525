"""Q*bert: a hand-written competent policy (same format and observation keys as games/scaffolds/qbert.py).

Map Q*bert and the enemies onto the pyramid's cells, remember which cubes Q*bert has stood on this round, and
hop (never off the pyramid) toward the nearest unvisited cube along cells that no enemy occupies or is about to
land on.
"""

import tracing as trace

GAME = "qbert"

CUBES = ((68, 34), (56, 62), (84, 62), (44, 91), (68, 91), (96, 91), (32, 120), (56, 120), (84, 120), (108, 120),
         (20, 149), (44, 149), (68, 149), (96, 149), (120, 149), (8, 178), (32, 178), (56, 178), (84, 178),
         (108, 178), (132, 178))
CELLS = [(r, c) for r in range(6) for c in range(r + 1)]
STAND = {cell: (CUBES[i][0] + 6, CUBES[i][1] - 17) for i, cell in enumerate(CELLS)}  # Q*bert's x, y on a cube
SOFT = 8        # cost of a cell an enemy may reach in two hops
WAIT_COST = 3   # cost of standing still one decision
LURE_DIST = 4   # Coily this close (rows + columns): head for a flying disk
MOVES = {2: (-1, 0), 3: (1, 1), 4: (-1, -1), 5: (1, 0)}  # UP upper-right, RIGHT lower-right, LEFT upper-left, DOWN lower-left


def _cell(x, y, tol=10):
    best, bd = None, tol
    for cell, (sx, sy) in STAND.items():
        d = abs(sx - x) + abs(sy - y) / 2
        if d < bd:
            best, bd = cell, d
    return best


def _valid(cell):
    return 0 <= cell[1] <= cell[0] <= 5


@trace.model
class Policy(trace.Module):

    def __init__(self):
        self.visited = set()

    def __call__(self, obs):
        situation = self.analyze_situation(obs)
        return self.select_action(situation, obs)

    @trace.bundle(trainable=True)
    def analyze_situation(self, obs):
        """Q*bert's cell (when standing), unsafe cells, and the round's visited cubes."""
        player = obs.get("Player")
        if len(self.visited) >= 21:  # all cubes stood on: a new round
            self.visited = set()
        if player is None:
            return {"player_x": 80, "player_y": 50, "nearest_enemy": None, "nearest_friendly": None,
                    "danger_above": False, "cell": None}
        standing = player["dx"] == 0 and player["dy"] == 0
        cell = _cell(player["x"], player["y"], 4) if standing else None
        if cell is not None:
            self.visited.add(cell)
        danger = {}  # cell -> cost: 100 where an enemy is or lands next, SOFT where it may land after that

        def mark(c, cost):
            if danger.get(c, 0) < cost:
                danger[c] = cost

        nearest = None
        coily = None
        for e in obs.get("Enemies", []):
            ec = _cell(e["x"], e["y"], 14)
            if ec is None:
                continue
            mark(ec, 100)
            r, c = ec
            if e["type"] == "Coily":
                coily = ec
            if e["type"] == "Coily":  # chases: every neighbour now, their neighbours next
                for dr, dc in MOVES.values():
                    mark((r + dr, c + dc), 100)
                    for dr2, dc2 in MOVES.values():
                        mark((r + dr + dr2, c + dc + dc2), SOFT)
            else:  # balls bounce downward
                mark((r + 1, c), 100)
                mark((r + 1, c + 1), 100)
                for k in range(3):
                    mark((r + 2, c + k), SOFT)
            if nearest is None or abs(e["x"] - player["x"]) + abs(e["y"] - player["y"]) < \
                    abs(nearest["x"] - player["x"]) + abs(nearest["y"] - player["y"]):
                nearest = e
        unsafe = {c for c, v in danger.items() if v >= 100}
        return {"player_x": player["x"], "player_y": player["y"], "nearest_enemy": nearest,
                "nearest_friendly": None, "danger_above": False, "cell": cell, "unsafe": unsafe,
                "visited": set(self.visited), "danger": danger,
                "coily": coily, "left_disk": any(d["x"] < 80 for d in obs.get("Disks", [])),
                "right_disk": any(d["x"] >= 80 for d in obs.get("Disks", []))}

    @trace.bundle(trainable=True)
    def select_action(self, situation, obs):
        """Hop to the safe neighbour closest (by hops) to an unvisited cube; NOOP in mid-hop."""
        cell = situation.get("cell")
        if cell is None:
            return 0
        unsafe, visited = situation["unsafe"], situation["visited"]
        coily = situation["coily"]
        exits = {}  # disk rides: LEFT off (4, 0), UP off (4, 4); Coily follows and falls (500 pts)
        if situation["left_disk"]:
            exits[(4, 0)] = 4
        if situation["right_disk"]:
            exits[(4, 4)] = 2
        lure = coily is not None and exits and abs(coily[0] - cell[0]) + abs(coily[1] - cell[1]) <= LURE_DIST
        if lure and cell in exits:
            return exits[cell]
        # BFS distances (in hops, through safe cells) to the nearest target: unvisited cubes, or disk cells
        targets = list(exits) if lure else [c for c in CELLS if c not in visited]
        dist = {c: 0 for c in targets if c not in unsafe}
        frontier = list(dist)
        while frontier:
            nxt = []
            for c in frontier:
                for dr, dc in MOVES.values():
                    n = (c[0] - dr, c[1] - dc)
                    if _valid(n) and n not in dist and n not in unsafe:
                        dist[n] = dist[c] + 1
                        nxt.append(n)
            frontier = nxt
        danger = situation["danger"]
        best, best_cost = 0, danger.get(cell, 0) + WAIT_COST  # NOOP: stay on this cube
        for action, (dr, dc) in MOVES.items():
            n = (cell[0] + dr, cell[1] + dc)
            if not _valid(n):
                continue
            cost = danger.get(n, 0) + dist.get(n, 30) + (0 if n in visited else -1)
            if cost < best_cost:
                best, best_cost = action, cost
        return best
