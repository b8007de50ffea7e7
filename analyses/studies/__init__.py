"""Studies: seeded experiments behind ``implantplan analyze ...`` and the checks of the
fast models against their exact references."""
