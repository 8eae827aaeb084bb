//! Local east/north displacements between GNSS fixes (SPEC §4). Owner: data/evidence work.
