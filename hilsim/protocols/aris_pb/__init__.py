"""Generated protobuf modules for the ARIS contract in ``protocols/aris/*.proto``.

Do not edit the ``*_pb2.py`` / ``*_pb2.pyi`` files: regenerate them after a
change to a .proto file with protoc from grpcio-tools (any venv; the runtime
``protobuf`` must be at least the version named in the generated files; the
committed ones come from grpcio-tools 1.85.1, libprotoc 35.1, gencode 7.35.1,
which pyproject.toml's ``protobuf`` pin matches)::

    python -m grpc_tools.protoc -Iprotocols/aris --python_out=hilsim/protocols/aris_pb \\
        --pyi_out=hilsim/protocols/aris_pb protocols/aris/*.proto

tests/protocols/test_aris.py checks that these modules match the .proto files
when grpc_tools is installed.
"""
