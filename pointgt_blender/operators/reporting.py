"""One way for operators to report errors: `@reports_errors("...")` on `execute`."""
from __future__ import annotations

import functools

from core.util.errors import PointGTError


def reports_errors(action: str):
    """Decorator for `Operator.execute`: a PointGTError becomes its own message as an ERROR report, any other
    exception '<action> failed: <type>: <message>' (never a traceback in the artist's face); both cancel the
    operator. `action` may name the active object as '{obj}'."""
    def deco(execute):
        @functools.wraps(execute)
        def wrapper(self, context):
            try:
                return execute(self, context)
            except PointGTError as exc:
                self.report({'ERROR'}, str(exc))
            except Exception as exc:  # an operator must never take Blender down
                name = getattr(getattr(context, "active_object", None), "name", "")
                self.report({'ERROR'}, f"{action.format(obj=name)} failed: {type(exc).__name__}: {exc}")
            return {'CANCELLED'}
        return wrapper
    return deco
