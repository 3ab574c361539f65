"""Run inside `unshare -rm` by tests/test_service_hardening2.py: the app with its SQLite database on a 1-MB
tmpfs mounted at argv[1] (blobs under argv[2]); fill the tmpfs, upload argv[3] (prints "FULL <status>
<detail>"), count the flights ("LISTED <n>"), free the tmpfs, upload again ("FREED <status>")."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

if __name__ == "__main__":
    mount, home, csv = Path(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3])
    subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "none", str(mount)], check=True)
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from utils.service import running_app, upload

    with running_app(home, database_url=f"sqlite:///{mount / 'learnest.db'}") as client:
        filler = mount / "filler"
        with open(filler, "wb", buffering=0) as handle:   # every byte of the tmpfs
            try:
                while True:
                    handle.write(b"\0" * 4096)
            except OSError:
                pass
        try:
            full = upload(client, csv)
            print("FULL", full.status_code, full.json().get("detail"), flush=True)
            print("LISTED", client.get("/flights").json()["total"], flush=True)
        finally:
            filler.unlink()
        freed = upload(client, csv)
        print("FREED", freed.status_code, flush=True)
