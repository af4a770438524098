# `pillarseg plot` (engine/render/plot.cpp, engine/util/metrics_log.cpp): FreeType draws the
# text of the charts (the DejaVu Sans font is found at run time), nlohmann-json reads
# metrics.jsonl. Debian packages libfreetype-dev and nlohmann-json3-dev (scripts/install-deps.sh).
find_package(Freetype REQUIRED)
find_package(nlohmann_json 3.9 REQUIRED)
