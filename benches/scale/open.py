"""Opening a session on two planets served by one `quincunx serve`, alternating (issue 22's
open-time bar), from the repository root:

    python3 benches/scale/open.py bundled=quincunx-demo/earth big=<planet repo> [runs] \
        >> benches/scale/open.jsonl

`runs` (default 15) rounds of `quincunx fly --json` of the distant view (the whole Earth
from 40,000 km) on each repository in turn; one JSON line with the medians of
`session_open_ms` and `client_peak_rss_mb` and their ratios (second over first).
"""
import json, os, socket, statistics, subprocess, sys, tempfile, time

Q = os.environ.get("QUINCUNX", "target/release/quincunx")
args = [a for a in sys.argv[1:] if "=" in a]
runs = int(next((a for a in sys.argv[1:] if "=" not in a), "15"))
repos = dict(a.split("=", 1) for a in args)
r = 6_371_008.8 + 4.0e7
d = [1.0, 0.3, 0.5]
ln = sum(x * x for x in d) ** 0.5
path = os.path.join(tempfile.mkdtemp(), "distant.json")
json.dump({"legs": [{"duration_s": 3, "jump": True, "settle_s": 0.5,
                     "from": {"eye": [x / ln * r for x in d], "target": [0, 0, 0]}}]},
          open(path, "w"))
s = socket.socket(); s.bind(("127.0.0.1", 0)); port = s.getsockname()[1]; s.close()
cmd = [Q, "serve", "--addr", f"127.0.0.1:{port}"]
for name, p in repos.items():
    cmd += ["--repo", f"{name}={p}"]
server = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
for line in server.stdout:
    if "serving on" in line:
        break
figures = {name: {"session_open_ms": [], "client_peak_rss_mb": []} for name in repos}
try:
    for _ in range(runs):
        for name in repos:
            o = subprocess.run([Q, "fly", "--json", "--allow-unfinished", "--url", f"http://127.0.0.1:{port}",
                                "--repo", name, "--path", path],
                               capture_output=True, text=True, check=True)
            j = json.loads(o.stdout)
            for k in figures[name]:
                figures[name][k].append(j[k])
finally:
    server.kill()
out = {"when": time.strftime("%Y-%m-%dT%H:%M:%S"), "runs": runs, "repos": repos}
for name, f in figures.items():
    out[name] = {k: statistics.median(v) for k, v in f.items()}
names = list(repos)
if len(names) == 2:
    a, b = names
    out["ratio"] = {k: out[b][k] / out[a][k] for k in out[a]}
print(json.dumps(out))
