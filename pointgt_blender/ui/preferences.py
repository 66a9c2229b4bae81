"""Add-on preferences: PyTorch status, the Install PyTorch button, and an optional existing site-packages."""
import os
import subprocess
import tempfile

import bpy

from ..bridge import deps

# The add-on's own package (preferences are keyed by it), one level above this ui/ subpackage.
ADDON_PACKAGE = __package__.rpartition(".")[0]

_added_paths: list[str] = []  # sys.path entries this add-on added (removed again on unregister)
_job: dict = {}  # the running background install: {"proc", "log", "target"}
_last_result = {"text": ""}


def user_site_dir(create: bool = True) -> str:
    """The add-on's private site-packages (inside Blender's user extension folder)."""
    try:
        return bpy.utils.extension_path_user(ADDON_PACKAGE, path="site-packages", create=create)
    except Exception:  # installed as a legacy add-on: no extension folder
        path = os.path.join(bpy.utils.user_resource('SCRIPTS', path="pointgt"), "site-packages")
        if create:
            os.makedirs(path, exist_ok=True)
        return path


def prefs():
    addon = bpy.context.preferences.addons.get(ADDON_PACKAGE)
    return addon.preferences if addon else None


def update_sys_path() -> None:
    """Put the add-on's site-packages and the user's extra folder on sys.path; torch is looked for again lazily
    (importing it costs seconds, so registering never does)."""
    for path in _added_paths:
        deps.remove_site_dir(path)
    _added_paths.clear()
    p = prefs()
    candidates = [user_site_dir(create=False)]
    if p and p.site_packages.strip():
        candidates.append(bpy.path.abspath(p.site_packages.strip()))
    for path in candidates:
        if deps.add_site_dir(path):
            _added_paths.append(os.path.abspath(path))
    deps.forget_status()


def remove_sys_path() -> None:
    for path in _added_paths:
        deps.remove_site_dir(path)
    _added_paths.clear()


def _on_site_packages(self, _context):
    update_sys_path()


def _finish_install(returncode: int, log: str) -> str:
    update_sys_path()
    status = deps.torch_status(refresh=True)
    if returncode == 0 and status.available:
        text = f"Installed: {status.message}"
    elif returncode == 0:
        text = f"pip finished but torch does not import: {status.problem}"
    else:
        text = f"pip failed (exit {returncode}): {deps.tail(log)}"
    _last_result["text"] = text
    return text


def _poll_job():
    """bpy.app.timers callback: check the background pip process; stop when it is done."""
    proc = _job.get("proc")
    if proc is None:
        return None
    if proc.poll() is None:
        return 1.0
    with open(_job["log"], encoding="utf-8", errors="replace") as fh:
        log = fh.read()
    _job.clear()
    _finish_install(proc.returncode, log)
    for window in bpy.context.window_manager.windows:
        for area in window.screen.areas:
            area.tag_redraw()
    return None


class POINTGT_OT_install_torch(bpy.types.Operator):
    """Download and install the CPU build of PyTorch into this add-on's folder (needs a network connection)"""
    bl_idname = "pointgt.install_torch"
    bl_label = "Install PyTorch"
    bl_options = {'REGISTER', 'INTERNAL'}

    synchronous: bpy.props.BoolProperty(name="Wait", default=False,
                                        description="Block Blender until pip is done (always so without a UI)")
    requirement: bpy.props.StringProperty(name="Requirement", default=deps.TORCH_REQUIREMENT)
    index_url: bpy.props.StringProperty(name="Index URL", default=deps.TORCH_CPU_INDEX,
                                        description="Package index; empty installs offline from 'Wheel folder'")
    find_links: bpy.props.StringProperty(name="Wheel folder", subtype='DIR_PATH', default="")

    @classmethod
    def poll(cls, context):
        if _job:
            cls.poll_message_set("An installation is already running")
            return False
        return True

    def execute(self, context):
        try:
            target = user_site_dir(create=True)
            if not deps.pip_available():
                boot = subprocess.run(deps.ensurepip_command(), capture_output=True, text=True)
                if boot.returncode != 0:
                    self.report({'ERROR'}, f"Blender's Python has no pip and ensurepip failed: "
                                           f"{deps.tail(boot.stdout + boot.stderr)}")
                    return {'CANCELLED'}
            cmd = deps.pip_install_command(target, tuple(self.requirement.split()), self.index_url or None,
                                           bpy.path.abspath(self.find_links) if self.find_links else None)
            if self.synchronous or bpy.app.background:
                proc = subprocess.run(cmd, capture_output=True, text=True)
                text = _finish_install(proc.returncode, proc.stdout + proc.stderr)
                ok = proc.returncode == 0
                self.report({'INFO'} if ok else {'ERROR'}, text)
                return {'FINISHED'} if ok else {'CANCELLED'}
            fd, log = tempfile.mkstemp(prefix="pointgt-pip-", suffix=".log")
            with os.fdopen(fd, "w") as fh:
                proc = subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT)
            _job.update(proc=proc, log=log, target=target)
            _last_result["text"] = f"Installing {self.requirement} into {target} ..."
            bpy.app.timers.register(_poll_job, first_interval=1.0)
        except Exception as exc:
            self.report({'ERROR'}, f"Could not start the PyTorch installation: {type(exc).__name__}: {exc}")
            return {'CANCELLED'}
        self.report({'INFO'}, _last_result["text"])
        return {'FINISHED'}


class POINTGT_OT_check_dependencies(bpy.types.Operator):
    """Look for PyTorch again (after installing it yourself or changing the site-packages folder)"""
    bl_idname = "pointgt.check_dependencies"
    bl_label = "Check Again"
    bl_options = {'REGISTER', 'INTERNAL'}

    def execute(self, context):
        try:
            update_sys_path()
            status = deps.torch_status(refresh=True)
        except Exception as exc:
            self.report({'ERROR'}, f"Checking dependencies failed: {exc}")
            return {'CANCELLED'}
        self.report({'INFO'} if status.available else {'WARNING'}, status.message)
        return {'FINISHED'}


class SidebarPanel:
    """Mixin of the PointGT sidebar tabs (3D View, Image Editor): their label and category, and the PyTorch status
    on top; subclasses set bl_idname and bl_space_type and draw the rest in `draw_body`."""
    bl_label = "PointGT"
    bl_region_type = 'UI'
    bl_category = "PointGT"

    def draw(self, context):
        draw_dependency_status(self.layout)
        self.draw_body(context, self.layout)

    def draw_body(self, context, layout) -> None:
        raise NotImplementedError


def draw_dependency_status(layout) -> None:
    """The PyTorch status box, shared by the preferences and the sidebar panel."""
    status = deps.torch_status()
    box = layout.box()
    if status.available:
        box.label(text=status.message, icon='CHECKMARK')
    else:
        box.label(text="PyTorch is missing: rendering and preview are off", icon='ERROR')
        col = box.column(align=True)
        col.scale_y = 0.8
        for line in _wrap(status.problem, 70):
            col.label(text=line)
    if _last_result["text"]:
        box.label(text=_last_result["text"][:200], icon='INFO')


def _wrap(text: str, width: int) -> list[str]:
    words, lines, cur = text.split(), [], ""
    for word in words:
        if len(cur) + len(word) + 1 > width and cur:
            lines.append(cur)
            cur = word
        else:
            cur = f"{cur} {word}".strip()
    return lines + ([cur] if cur else [])


class PointGTPreferences(bpy.types.AddonPreferences):
    bl_idname = ADDON_PACKAGE

    site_packages: bpy.props.StringProperty(
        name="Existing site-packages", subtype='DIR_PATH', update=_on_site_packages,
        description="Use PyTorch from another Python environment (it must be built for Blender's Python version)")

    def draw(self, context):
        layout = self.layout
        draw_dependency_status(layout)
        row = layout.row()
        row.operator(POINTGT_OT_install_torch.bl_idname, icon='IMPORT',
                     text=f"Install PyTorch ({deps.TORCH_REQUIREMENT}, CPU, about 200 MB)")
        row.operator(POINTGT_OT_check_dependencies.bl_idname, icon='FILE_REFRESH')
        layout.label(text=f"Installs into: {user_site_dir(create=False)}")
        layout.prop(self, "site_packages")
        problem = deps.check_site_packages(bpy.path.abspath(self.site_packages)) if self.site_packages else ""
        if problem:
            layout.label(text=problem, icon='ERROR')


CLASSES = (POINTGT_OT_install_torch, POINTGT_OT_check_dependencies, PointGTPreferences)
