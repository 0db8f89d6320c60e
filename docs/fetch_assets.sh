#!/usr/bin/env bash
# Fetch the scripts the docs site serves itself into docs/javascripts/ (gitignored):
# mermaid.min.js, which draws the ```mermaid diagrams. mkdocs-material otherwise loads
# mermaid from a CDN, and a page opened offline shows the diagram's source as text.
# mkdocs.yml lists the file under extra_javascript; material then uses it.
#
# Run it once before `mkdocs build` or `mkdocs serve` (.ci/run does). It needs npm
# and the npm registry; it does nothing when the pinned version is already there.
# The tarball is checked against the pinned integrity before anything is copied.
set -euo pipefail
cd "$(dirname "$0")"

# mermaid 11: the major version mkdocs-material 9 is written for.
MERMAID_VERSION=11.17.2
MERMAID_INTEGRITY=sha512-V6K3C8EBdEsPFZXSKMJe6ppQOENxuHARr9GvHX4hh47lAbhMRD9qf4oEK7LoaRQxULMa80/qt5gHO73aCleBBg==

target=javascripts/mermaid.min.js
stamp=javascripts/.mermaid-version
if [[ -f "$target" && -f "$stamp" && "$(cat "$stamp")" == "$MERMAID_VERSION" ]]; then
    exit 0
fi
if ! command -v npm >/dev/null; then
    echo "fetch_assets: npm not found; install Node.js (npm) to fetch mermaid $MERMAID_VERSION" >&2
    exit 1
fi

work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
if ! (cd "$work" && npm pack --loglevel=error "mermaid@$MERMAID_VERSION" >/dev/null); then
    echo "fetch_assets: npm pack mermaid@$MERMAID_VERSION failed (is the npm registry reachable?)" >&2
    exit 1
fi
tarball="$work/mermaid-$MERMAID_VERSION.tgz"
actual="sha512-$(node -e 'process.stdout.write(require("crypto").createHash("sha512")
    .update(require("fs").readFileSync(process.argv[1])).digest("base64"))' "$tarball")"
if [[ "$actual" != "$MERMAID_INTEGRITY" ]]; then
    echo "fetch_assets: mermaid-$MERMAID_VERSION.tgz is $actual, expected $MERMAID_INTEGRITY" >&2
    exit 1
fi
tar -xzf "$tarball" -C "$work" package/dist/mermaid.min.js
mkdir -p javascripts
# Into place by rename, so an interrupted fetch never leaves half a script behind.
cp "$work/package/dist/mermaid.min.js" "$target.partial"
mv "$target.partial" "$target"
echo "$MERMAID_VERSION" >"$stamp"
echo "fetch_assets: docs/$target (mermaid $MERMAID_VERSION)"
