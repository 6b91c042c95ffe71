"""The truth suite: known edits drawn at random from a printed seed (`cases`), placed on their
scenes (`scenes`), run (`run`), scored and charted (`report`) and set against another run of the
draw (`compare`); `cli.main` is scripts/truth_suite.py."""
