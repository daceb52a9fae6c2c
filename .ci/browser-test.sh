#!/usr/bin/env bash
# The HTML report in a real browser: headless Chromium from Debian renders the seed study's
# report (with a [consistency] section, so it has verdicts) and this script asserts
#   * no console message (page errors reach the console too), with a probe message that must
#     be seen, so a Chromium that logs nothing cannot pass;
#   * every figure rendered with a non-zero size, and the verdict table present with rows
#     (counted by a script injected into a copy of the report, read back with --dump-dom);
#   * no horizontal overflow of the page at phone width (390 px);
#   * a 1280 px screenshot that is not blank (PNG decoded with zlib, no PIL needed);
#   * the print stylesheet produces a PDF.
# Usage: .ci/browser-test.sh [KFMC_BINARY] [--update-reference]
# --update-reference copies the screenshot to docs/src/figures/report.png.
set -euo pipefail
cd "$(dirname "$0")/.."
KFMC=${1:-target/release/kfmc}
UPDATE=${2:-}
t0=$(date +%s)

if ! command -v chromium >/dev/null 2>&1; then
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends chromium >/dev/null
fi
t1=$(date +%s)
chromium --version

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
# The seed study as shipped, with its consistency tested, at 50 runs.
{ cat experiments/planar_seed_study.toml; printf '\n[consistency]\nalpha = 0.05\n'; } > "$work/seed.toml"
"$KFMC" run "$work/seed.toml" --runs 50 --out "$work/seed" --quiet
"$KFMC" report "$work/seed"
report="$work/seed/report.html"

# Chromium wants a writable profile and no sandbox as root (CI runs as root).
browse() {
    chromium --headless --no-sandbox --disable-gpu --hide-scrollbars \
        --user-data-dir="$work/profile" --no-first-run --disable-extensions \
        --enable-logging=stderr --v=0 "$@"
}

# A copy of the report with a probe at the end of <body>: it forces layout, counts the figures
# with a non-zero rendered size and the verdict table's rows, and writes them into the DOM.
probe='<script>(function(){
var figs=document.querySelectorAll("figure svg, figure img"),ok=0;
figs.forEach(function(e){var r=e.getBoundingClientRect();if(r.width>0&&r.height>0)ok++;});
var v=document.getElementById("verdict-table");
var rows=v?v.querySelectorAll("tbody tr").length:0;
var d=document.documentElement;
var p=document.createElement("pre");p.id="kfmc-probe";
p.textContent="figures="+figs.length+" rendered="+ok+" verdict_rows="+rows+" overflow="+(d.scrollWidth>window.innerWidth?1:0)+" end";
document.body.appendChild(p);console.log("kfmc-probe-alive");})();</script>'
python3 - "$report" "$work/probe.html" "$probe" <<'PY'
import sys
html = open(sys.argv[1], encoding="utf-8").read()
assert html.count("</body>") == 1
open(sys.argv[2], "w", encoding="utf-8").write(html.replace("</body>", sys.argv[3] + "\n</body>"))
PY

check_probe() { # $1: window size, $2: name
    browse --window-size="$1" --dump-dom "file://$work/probe.html" >"$work/$2.dom" 2>"$work/$2.log" || {
        cat "$work/$2.log"; echo "chromium failed ($2)"; exit 1; }
    grep -q 'kfmc-probe-alive' "$work/$2.log" || {
        cat "$work/$2.log"; echo "no console output captured ($2): cannot check for errors"; exit 1; }
    if grep 'CONSOLE' "$work/$2.log" | grep -v 'kfmc-probe-alive'; then
        echo "console messages in the report ($2)"; exit 1
    fi
    line=$(grep -o 'figures=[0-9]* rendered=[0-9]* verdict_rows=[0-9]* overflow=[01] end' "$work/$2.dom") || {
        echo "probe result missing ($2)"; exit 1; }
    echo "$2: $line"
    read -r figs ok rows overflow < <(echo "$line" | sed -E 's/figures=([0-9]+) rendered=([0-9]+) verdict_rows=([0-9]+) overflow=([01]) end/\1 \2 \3 \4/')
    expected=$(grep -c '<figure' "$report")
    [ "$figs" -eq "$expected" ] || { echo "$figs figures in the DOM, $expected in the file"; exit 1; }
    [ "$figs" -gt 0 ] && [ "$ok" -eq "$figs" ] || { echo "$ok of $figs figures rendered"; exit 1; }
    [ "$rows" -gt 0 ] || { echo "no verdict table"; exit 1; }
    [ "$overflow" -eq 0 ] || { echo "the page overflows horizontally at $1"; exit 1; }
}
check_probe 1280,900 desktop
check_probe 390,844 phone

# The screenshot of the report as written (no probe).
browse --window-size=1280,2400 --screenshot="$work/report.png" "file://$report" 2>"$work/shot.log" || {
    cat "$work/shot.log"; exit 1; }
python3 - "$work/report.png" <<'PY'
import struct, sys, zlib
data = open(sys.argv[1], "rb").read()
assert data[:8] == b"\x89PNG\r\n\x1a\n", "not a PNG"
pos, idat, hdr = 8, b"", None
while pos < len(data):
    n, kind = struct.unpack(">I4s", data[pos:pos + 8])
    body = data[pos + 8:pos + 8 + n]
    if kind == b"IHDR":
        hdr = struct.unpack(">IIBBBBB", body)
    elif kind == b"IDAT":
        idat += body
    pos += 12 + n
w, h, depth, ctype = hdr[0], hdr[1], hdr[2], hdr[3]
assert depth == 8 and ctype in (2, 6), f"unexpected PNG type {hdr}"
bpp = 3 if ctype == 2 else 4
raw, stride = zlib.decompress(idat), w * bpp
rows, prev, i = [], bytearray(stride), 0
for _ in range(h):
    f, line = raw[i], bytearray(raw[i + 1:i + 1 + stride])
    i += 1 + stride
    for x in range(stride):
        a = line[x - bpp] if x >= bpp else 0
        b = prev[x]
        c = prev[x - bpp] if x >= bpp else 0
        if f == 1: line[x] = (line[x] + a) & 255
        elif f == 2: line[x] = (line[x] + b) & 255
        elif f == 3: line[x] = (line[x] + (a + b) // 2) & 255
        elif f == 4:
            p = a + b - c
            pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
            line[x] = (line[x] + (a if pa <= pb and pa <= pc else b if pb <= pc else c)) & 255
    rows.append(bytes(line))
    prev = line
px = [r[x:x + 3] for r in rows[::4] for x in range(0, stride, bpp * 4)]
non_white = sum(1 for p in px if min(p) < 200) / len(px)
coloured = sum(1 for p in px if max(p) - min(p) > 60) / len(px)
colours = len(set(px))
mean = sum(sum(p) for p in px) / (3 * len(px))
var = sum((sum(p) / 3 - mean) ** 2 for p in px) / len(px)
print(f"screenshot {w}x{h}: {non_white:.1%} non-white, {coloured:.1%} coloured, {colours} colours, grey-level variance {var:.0f}")
assert non_white > 0.02 and coloured > 0.002 and colours > 50 and var > 100, "the screenshot looks blank"
PY

browse --print-to-pdf="$work/report.pdf" --no-pdf-header-footer "file://$report" 2>"$work/pdf.log" || {
    cat "$work/pdf.log"; exit 1; }
pages=$(python3 -c 'import re,sys; print(len(re.findall(rb"/Type\s*/Page(?!s)", open(sys.argv[1],"rb").read())))' "$work/report.pdf")
echo "print: $(stat -c %s "$work/report.pdf") bytes, $pages pages"
[ "$pages" -gt 0 ] || { echo "the printed report has no pages"; exit 1; }

if [ "$UPDATE" = "--update-reference" ]; then
    cp "$work/report.png" docs/src/figures/report.png
fi
t2=$(date +%s)
echo "browser test: $((t2 - t0)) s ($((t1 - t0)) s installing Chromium, $((t2 - t1)) s checking)"
