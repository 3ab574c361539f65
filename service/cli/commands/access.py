"""The handlers of `learnest tokens create|list|revoke` and `learnest audit`: no torch, no worker set-up."""
from __future__ import annotations

import json
import sys


def _tokens_create(args) -> int:
    """Make a token and print it once (service.local.access.create_token)."""
    from ...local.access import create_token

    token, row = create_token(args.name, args.scope)
    if args.json:
        print(json.dumps({**row, "token": token}, indent=2))
        return 0
    print(token)
    article = "an" if row["scope"] == "admin" else "a"
    print(f"learnest: {article} {row['scope']} token for {row['name']} (id {row['id']}); it is printed this once, "
          "the registry keeps only its SHA-256. Send it as 'Authorization: Bearer TOKEN' or 'X-API-Key: TOKEN', or "
          "sign in with it at /ui/signin.", file=sys.stderr)
    return 0


def _tokens_list(args) -> int:
    """Every token made, revoked ones too."""
    from ...local.access import list_tokens

    rows = list_tokens()
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    print(f"{len(rows)} token(s), {sum(r['revoked_at'] is None for r in rows)} not revoked")
    if rows:
        print(f"{'id':>4}  {'name':<20}{'scope':<7}{'made (UTC)':<21}{'by':<20}revoked (UTC)")
    for r in rows:
        revoked = f"{_when(r['revoked_at'])} by {r['revoked_by']}" if r["revoked_at"] else "-"
        print(f"{r['id']:>4}  {r['name']:<20}{r['scope']:<7}{_when(r['created_at']):<21}{r['created_by'] or '-':<20}"
              f"{revoked}")
    return 0


def _tokens_revoke(args) -> int:
    """Revoke a token by id or name: it fails at once on every server worker."""
    from ...local.access import revoke_token

    row = revoke_token(args.token)
    print(json.dumps(row, indent=2) if args.json else f"revoked token {row['id']} ({row['name']}, {row['scope']})")
    return 0


def _audit(args) -> int:
    """The newest entries of the audit log."""
    from ...local.access import audit_entries

    out = audit_entries(args.limit)
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    print(f"{out['total']} entr{'y' if out['total'] == 1 else 'ies'}" +
          (f", the newest {len(out['items'])}" if len(out["items"]) < out["total"] else ""))
    for e in out["items"]:
        print(f"{_when(e['at'])}  {e['actor']:<20}{e['action']:<18}{e['target']}")
    return 0


def _when(moment: str | None) -> str:
    return (moment or "")[:19].replace("T", " ")
