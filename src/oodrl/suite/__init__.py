"""The suite's machinery (SPEC §11, §12, §16, §21): the environments' pipelines (`environments`),
their DVC files and code stamps (`pipeline`), `oodrl check-params`' checks (`params_check`),
`oodrl suite run` (`run`), `oodrl suite try` (`try_detector`) and `oodrl new` (`new`)."""
