"""The upload flow of a capture: a manifest of files declared at creation (`manifest`), each
file sent resumably over tus 1.0.0 (`tus`: the protocol's headers and checksums; `files`: where
an upload's bytes land and when a file is complete), or a whole capture as one zip
(`archive`), staged on local disk (`staging`), then validated, imported and frozen into the
artifact store at commit (`commit`). The routes are `service.routers.uploads` and
`service.routers.captures`."""

__all__: list[str] = []
