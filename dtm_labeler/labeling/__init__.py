"""labeling subpackage."""
