"""The methods both clients have, listed once: each runs one operation of `api.client.ops`
with the client's `run`, so it returns the answer on `PhasecalClient` and an awaitable of
it on `AsyncPhasecalClient`, with the builder's name, signature and docstring on both."""

from __future__ import annotations

import functools
import inspect
from collections.abc import Callable, Coroutine
from typing import Any, Generic, ParamSpec, Protocol, TypeVar, overload

from api.client import ops

P = ParamSpec("P")
T = TypeVar("T")


class SyncRunner(Protocol):
    """A client whose `run` returns the answer."""

    def run(self, op: ops.Op[T], /) -> T:
        """The answer of `op`."""


class AsyncRunner(Protocol):
    """A client whose `run` is a coroutine."""

    def run(self, op: ops.Op[T], /) -> Coroutine[Any, Any, T]:
        """A coroutine giving the answer of `op`."""


class Operation(Generic[P, T]):
    """A client method running the operation `build` describes (same name and signature)."""

    def __init__(self, build: Callable[P, ops.Op[T]]) -> None:
        self.build = build
        self.__doc__ = build.__doc__
        # the builder's parameters; its return annotation (an Op) is not what the method gives
        self.signature = inspect.signature(build).replace(
            return_annotation=inspect.Signature.empty)

    @overload
    def __get__(self, client: None, owner: type) -> Operation[P, T]: ...

    @overload
    def __get__(self, client: AsyncRunner, owner: type
                ) -> Callable[P, Coroutine[Any, Any, T]]: ...

    @overload
    def __get__(self, client: SyncRunner, owner: type) -> Callable[P, T]: ...

    def __get__(self, client: Any, owner: type) -> Any:
        if client is None:
            return self
        build = self.build

        async def awaitable(*args: Any, **kwargs: Any) -> Any:
            return await client.run(build(*args, **kwargs))

        def blocking(*args: Any, **kwargs: Any) -> Any:
            return client.run(build(*args, **kwargs))

        method: Any = awaitable if inspect.iscoroutinefunction(client.run) else blocking
        functools.update_wrapper(method, build)
        method.__signature__ = self.signature
        return method


class Operations:
    """Every method of the clients that is one operation (a request and its answer)."""

    # -- any request
    request = Operation(ops.request)
    get = Operation(ops.get)
    post = Operation(ops.post)
    # -- resources
    health = Operation(ops.health)
    list_devices = Operation(ops.list_devices)
    list_rigs = Operation(ops.list_rigs)
    create_rig = Operation(ops.create_rig)
    get_rig = Operation(ops.get_rig)
    move_screen = Operation(ops.move_screen)
    camera_settings = Operation(ops.camera_settings)
    create_session = Operation(ops.create_session)
    list_sessions = Operation(ops.list_sessions)
    get_session = Operation(ops.get_session)
    get_plan = Operation(ops.get_plan)
    capture_pose = Operation(ops.capture_pose)
    resume_pose = Operation(ops.resume_pose)
    list_poses = Operation(ops.list_poses)
    get_pose = Operation(ops.get_pose)
    calibrate = Operation(ops.calibrate)
    quick_intrinsics = Operation(ops.quick_intrinsics)
    get_intrinsics = Operation(ops.get_intrinsics)
    list_calibrations = Operation(ops.list_calibrations)
    get_calibration = Operation(ops.get_calibration)
    calibrate_target_rig = Operation(ops.calibrate_target_rig)
    get_target_rig_calibration = Operation(ops.get_target_rig_calibration)
    export_target_rig = Operation(ops.export_target_rig)
    project = Operation(ops.project)
    unproject = Operation(ops.unproject)
    undistort_points = Operation(ops.undistort_points)
    create_batch = Operation(ops.create_batch)
    get_job = Operation(ops.get_job)
    list_jobs = Operation(ops.list_jobs)
    cancel_job = Operation(ops.cancel_job)
    # -- streamed uploads and downloads
    import_frames = Operation(ops.import_frames)
    import_maps = Operation(ops.import_maps)
    download = Operation(ops.download)
    download_file = Operation(ops.download_file)
    download_maps = Operation(ops.download_maps)
    download_frames = Operation(ops.download_frames)
    download_report = Operation(ops.download_report)
    export = Operation(ops.export)
