"""One `run`-style function per pipeline stage; the CLI parses paths and calls them."""
