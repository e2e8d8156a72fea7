#!/bin/sh
# Fills seeds/TARGET/ with seed inputs: small files written by make_seeds.py plus the
# third-party reference files (profilometry/ of this repository and, when present beside the
# checkout or at $SHARED, shared/data/surfaces/). Run from the fuzz/ directory. The seeds are
# not kept: corpus/TARGET/ is the kept corpus, grown from them and minimised (README.md).
set -e
python3 make_seeds.py seeds
S=${SHARED:-../../shared}/data/surfaces
add() { # TARGET FILE...
    t=$1; shift
    mkdir -p "seeds/$t"
    for f in "$@"; do [ -f "$f" ] && cp "$f" "seeds/$t/$(echo "$f" | tr / _)"; done
    return 0
}
add x3p ../profilometry/*.x3p $S/surfalize/*.x3p $S/surfacetopography/*.x3p
add gsf ../profilometry/*.gsf
add sdf_binary $S/sdfio/s1_tilt_pedestal.bin.sdf
add sdf_ascii $S/gwyddion/s1_tilt_pedestal.sdf
add sur ../profilometry/*.sur
add opd $S/instruments/wyko.opd ../profilometry/*.opd
add plu $S/instruments/sensofar.plu
add al3d ../profilometry/*.al3d
add tmd ../profilometry/*.tmd
add vk4 ../profilometry/*.vk4
add vk6 ../profilometry/*.vk6
add lext ../profilometry/*.lext
add frt ../profilometry/*.frt
add datx ../profilometry/*.datx
add opdx ../profilometry/*.opdx
add spm ../profilometry/*.spm
add plux ../profilometry/*.plux
add png_pcal ../profilometry/*.png
add tiff ../profilometry/*.tiff
