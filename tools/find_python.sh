#!/bin/sh
# Print the path of a Python of version $1 (e.g. 3.13) that runs here: `pythonX.Y` on PATH, then
# pyenv's versions, then the usual prefixes. Prints nothing (and exits 1) when there is none.
# Blender 5.1 and newer ship as bpy wheels for Python 3.13 only, so `make test` needs one.
want=$1
pyenv_root=$(pyenv root 2>/dev/null || echo "$HOME/.pyenv")
for candidate in "python$want" "$pyenv_root"/versions/"$want"*/bin/"python$want" \
        /usr/local/bin/"python$want" /usr/bin/"python$want" /opt/homebrew/bin/"python$want"; do
    # pyenv's shim is on PATH even where that version is not selected: check that it really runs it
    if "$candidate" -c "import sys; sys.exit(sys.version_info[:2] != tuple(map(int, '$want'.split('.'))))" \
            >/dev/null 2>&1; then
        command -v "$candidate" 2>/dev/null || echo "$candidate"
        exit 0
    fi
done
exit 1
