"""Serving and opening at scale (issue 22, item 6), from the repository root:

    python3 benches/scale/serve.py bundled=quincunx-demo/earth big=<planet repo> \
        >> benches/scale/serving.jsonl

Per round (3) and repository, each served alone by `quincunx serve` (defaults): the time
to its "serving on" line, its RSS then, `quincunx fly --json` of a distant view (the whole
Earth from 40,000 km) and of benches/trade/planet-jumps.json, then `quincunx loadtest`
(256 connections, 10 s) and the server's RSS after. One JSON line each.
"""
import json, subprocess, time, socket, sys, tempfile, os

Q = os.environ.get("QUINCUNX", "target/release/quincunx")
REPOS = dict(a.split("=", 1) for a in sys.argv[1:])
DISTANT = os.path.join(tempfile.mkdtemp(), "distant.json")
r = 6_371_008.8 + 4.0e7
d = [1.0, 0.3, 0.5]
ln = sum(x * x for x in d) ** 0.5
json.dump({"legs": [{"duration_s": 10, "jump": True, "settle_s": 0.5,
                     "from": {"eye": [x / ln * r for x in d], "target": [0, 0, 0]}}]},
          open(DISTANT, "w"))
JUMPS = "benches/trade/planet-jumps.json"


def free_port():
    s = socket.socket(); s.bind(("127.0.0.1", 0)); p = s.getsockname()[1]; s.close(); return p


def rss_kb(pid):
    for l in open(f"/proc/{pid}/status"):
        if l.startswith("VmRSS:"):
            return int(l.split()[1])


def serve(name, path):
    port = free_port()
    t0 = time.monotonic()
    p = subprocess.Popen([Q, "serve", "--addr", f"127.0.0.1:{port}", "--repo", f"{name}={path}"],
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    for line in p.stdout:
        if "serving on" in line:
            break
    up = (time.monotonic() - t0) * 1000
    return p, port, up


out = []
for rnd in range(3):
    for name, path in REPOS.items():
        p, port, up = serve(name, path)
        url = f"http://127.0.0.1:{port}"
        rss0 = rss_kb(p.pid)
        flies = {}
        for label, fp in [("distant", DISTANT), ("jumps", JUMPS)]:
            o = subprocess.run([Q, "fly", "--json", "--allow-unfinished", "--url", url, "--repo", name,
                                "--path", fp],
                               capture_output=True, text=True)
            fj = json.loads(o.stdout)
            flies[label] = {k: fj.get(k) for k in ["session_open_ms", "client_peak_rss_mb", "cracks",
                                                   "jumps_unfinished", "dag_bytes_max", "bytes_fetched"]}
        o = subprocess.run([Q, "loadtest", "--url", url, "--repo", name, "--connections", "256",
                            "--duration-s", "10", "--json", "--quiet"], capture_output=True, text=True)
        lt = json.loads(o.stdout)
        rss1 = rss_kb(p.pid)
        p.terminate(); p.wait()
        rec = {"round": rnd, "repo": name, "up_ms": up, "rss_start_kb": rss0, "rss_after_kb": rss1,
               "fly": flies, "loadtest": lt}
        out.append(rec)
        print(json.dumps(rec), flush=True)
